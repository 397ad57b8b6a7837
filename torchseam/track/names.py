"""The trackers' names, for the command line's parsers (``--tracker`` choices) without
importing torch or OpenCV: :mod:`torchseam.track.peers` builds them."""

#: every tracker :func:`torchseam.track.peers.make_tracker` builds, by name
TRACKERS = ("eakf-stc", "anchored", "stc", "tipm", "kcf", "csrt", "mosse")
