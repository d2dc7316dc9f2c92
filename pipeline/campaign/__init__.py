"""Monte Carlo campaigns: many runs of a scenario with dispersed config fields, as Ray tasks.

`spec` (the TOML spec and the per-run draws), `execute` (one run; the driver on Ray or in this
process; resume), `results` (campaign.parquet, campaign.duckdb, report.md). The campaign sits
above the stages (it runs their plans with the one executor) and below the command line.
"""
