"""Crater-based absolute navigation for lunar landers (Süslü, Kuran & Söken), as a batch pipeline.

Stages: catalogue ingest -> trajectory -> detection -> estimation -> scoring. The numerical core
(`pipeline.core`) is pure numpy/scipy; `pipeline.stages` hold the I/O glue.
"""

__version__ = "0.1.0"
