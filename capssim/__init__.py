"""capssim: camera-array colour-polarization super-resolution (CAPS), simulated and scored.

The package ``capssim`` holds the camera physics (operators, sensor, rendering, captures);
``reconstruct`` the reconstruction methods; ``eval`` the scoring. Imports go one way:
capssim never imports reconstruct or eval (the CLI in ``capssim.cli`` loads them lazily).
"""

import logging

__version__ = "0.2.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
