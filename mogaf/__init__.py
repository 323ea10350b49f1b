"""MoGaF: motion group-aware Gaussian forecasting.

Importing the package is cheap and never touches CUDA: heavy modules
(torch kernels, gsplat) are imported by the stages that need them.
"""

__version__ = "0.1.0"
