"""Shared core of the pomar distribution: flight-directory format, camera model, geodesy.

Everything here is light (numpy, scipy, pymap3d) so that `onboard`, `ground` and `sim`
can all import it without pulling in each other's heavy dependencies.
"""

__version__ = "0.1.0"
