"""sigrend: lighting and BRDF from photos of a known shape, in frequency space.

Layering (DESIGN.md, "The house"): pipeline.core <- pipeline.io <- stages, calib <- pipeline.runner
<- pipeline.cli.  This package imports no stage.
"""

__version__ = "0.1.0"

STAGES = ("linearize", "poses", "samples", "fit", "relight")  # what `sigrend run` runs, in this order
