"""kincal's maths: numpy in, numpy out (no HTTP, SQL or files).

The dense problems here are small (hundreds of columns at most), where multi-threaded BLAS costs
more than it saves and fights with worker processes for cores: default to one BLAS thread unless
the user set the variable. This must run before numpy is first imported.
"""

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")
