"""Names the simulator's command line offers (``--camera`` choices), without importing OpenCV:
:mod:`torchseam.sim.record` writes them."""

#: the cameras a simulated sequence can be written as: colour (BGR, as rendered), or a mono
#: camera behind the 650 nm band-pass at 8 or 16 bit (:func:`torchseam.sim.variants.to_mono`)
CAMERAS = ("colour", "mono", "mono16")
