"""Evaluation of runs: metrics and summaries of a log, replay and verify, the regression suite,
plots. Reads logs and configs; never touches the bus."""
