"""dyngs: dynamic (4D) Gaussian Splatting."""

__version__ = "0.1.0"
