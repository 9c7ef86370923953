"""carotid: from a CT angiogram of the neck to a verified blood-flow simulation of the carotid bifurcation."""

__version__ = "0.1.0"
