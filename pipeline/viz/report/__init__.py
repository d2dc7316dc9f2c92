"""report.md and its figures (matplotlib): the paper's Figs. 4-8 and Table 1, with the CRLB.

Run reports: crater counts against time with the altitude (Fig. 4), position and attitude errors
(Figs. 5-6) with the +-3 sqrt(CRLB) band, the window tables, and the errors by number of craters
used (summaries pooled over frames are dominated by the few frames with 3-5 craters). Sweep
reports: Table 1 beside the paper's and position errors per cap (Figs. 7-8). Published numbers
come from a study module (`pipeline.studies.suslu2025` by default); labels, units and colours
from `pipeline.vocab`. Every axis carries one unit.
"""
