"""kincal's maths: numpy in, numpy out (no HTTP, SQL or files).

The dense problems here are small (hundreds of columns at most), where multi-threaded BLAS costs
more than it saves and fights with worker processes for cores (measured: a 42×42 ``eigh`` takes
20 ms instead of 0.4 ms on a busy 2-core machine): default to one BLAS thread unless the user set
one of the variables. Environment variables only act before numpy is first imported; when numpy
came first (a script importing it before ``solver``) the running BLAS is limited instead.
"""

import os
import sys

_BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
_user_chose = any(name in os.environ for name in _BLAS_THREAD_VARIABLES)
for _variable in _BLAS_THREAD_VARIABLES:
    os.environ.setdefault(_variable, "1")
if not _user_chose and "numpy" in sys.modules:
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
