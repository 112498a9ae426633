"""Studies over many runs: sweeps and Monte-Carlo (``ballbeam sweep``) and tuning
(``ballbeam tune``), evaluated on a Dask cluster.

``spec`` reads a sweep spec and expands it into points (pure: no I/O past reading the spec);
``points`` evaluates one point on a worker (offline or over the bus, with the designed
controller cached per worker); ``store`` keeps one result per point, content-addressed, so a
sweep resumes; ``cluster`` starts or joins the Dask cluster; ``engine`` runs the points on it;
``report`` prints the summary and draws the plots; ``tune`` chooses a design with Optuna.

Dask, pandas, pyarrow and Optuna are the ``studies`` extra and are imported only here.
"""
