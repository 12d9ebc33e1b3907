"""clscatter: single scattering in participating media, rendered with OpenCL."""
__version__ = "0.1.0"
