"""ballbeam-hil: optimal tracking controller bench for the SRV02 ball-and-beam."""

import os

# The core works on 4×4 matrices: a second BLAS thread only adds wake-up latency, which on a
# loaded machine costs far more than the product itself. Must precede numpy.
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")
