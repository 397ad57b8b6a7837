"""The live loop's names the command line's parsers need (``--fault`` choices), in a module
that imports neither torch nor OpenCV: :mod:`torchseam.live.demo` injects them."""

#: the faults ``torchseam demo --fault`` injects mid-segment (:func:`torchseam.live.demo.run_demo`)
FAULTS = ("dropped-frames", "arc-flash", "laser-off", "packet-loss", "controller-silence")
