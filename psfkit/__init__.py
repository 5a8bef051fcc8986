"""psfkit: characterize the shift-variant PSF of a lensless (diffuser) camera."""

__version__ = "0.1.0"
