"""Where the processes of ``ballbeam`` start: the ``ballbeam`` command, ``python -m ballbeam``
and ``python -m ballbeam_emulator`` (the nodes, the sweep's embedded workers, the regression's
runs all start here). It imports nothing heavy, so its limits precede numpy.
"""

from __future__ import annotations

import os

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def limit_blas_threads() -> None:
    """One BLAS thread in this process and the ones it starts, unless the user chose a count:
    the core works on 4×4 matrices, where a second thread only adds wake-up latency, which on
    a loaded machine costs far more than the product. Only a process's own entry point calls
    this, before numpy is imported (OpenBLAS reads the variables when it loads)."""
    for variable in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(variable, "1")


def main() -> int:
    """The ``ballbeam`` command."""
    limit_blas_threads()
    from ballbeam.cli import main as cli_main

    return cli_main()
