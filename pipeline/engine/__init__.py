"""The engine: stage declarations, the DAG derived from them, per-stage code fingerprints and the
one executor that runs a plan of stage invocations on a run store (for `run` and each run of a
campaign, `pipeline.campaign`)."""
