"""pmvir: polarimetric multi-view inverse rendering from colour-polarization captures."""

__version__ = "0.1.0"
