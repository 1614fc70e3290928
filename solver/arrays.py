"""The NumPy array types of the maths, defined once for every module: ``FloatArray`` (float64
values, units as each name says), ``IntArray`` (indices and counts, ``np.intp``) and
``BoolArray`` (masks)."""

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]
