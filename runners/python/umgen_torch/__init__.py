"""Runs umgen export bundles in plain PyTorch.

>>> import umgen_torch
>>> bundle = umgen_torch.load("BUNDLE")              # checks files, builds the model
>>> frames = bundle.generate([[]], frames=2, seed=0)  # one scene from nothing, two frames of N ids
"""

from .bundle import Bundle, BundleError, UnsupportedSetting, load
from .model import UMGen

__all__ = ["Bundle", "BundleError", "UnsupportedSetting", "UMGen", "load"]
