"""Physical and rig constants, defined once (DESIGN.md: the paper's values).

Two fields of view, because the paper has two cameras: its synthetic renderer uses 63.4° for the
480x360 training images, and its real captures' calibrated camera (the `cam*.txt` rig) has
63.349°. Generated data, the shipped weights and the tests use the first; `import-paper` the second.
"""

IOR_AIR = 1.0003
IOR_GLASS = 1.4723

PAPER_RENDER_FOV_X_DEG = 63.4  # the paper's synthetic images (and ours)
PAPER_CAPTURE_FOV_X_DEG = 63.349  # the paper's real capture camera
PAPER_IMAGE_SIZE = (480, 360)  # width, height of the paper's rendered images
