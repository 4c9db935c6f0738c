"""lanevil_train: robustness of lane perception to environmental illusions (LanEvil++)."""

__version__ = "0.1.0"
