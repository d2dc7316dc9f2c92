"""The engine: stage declarations, the DAG derived from them, per-stage code fingerprints and the
one executor that runs a plan of stage invocations (for `run`, `sweep` and campaigns) on a runner
(in-process, a local process pool; Ray next)."""
