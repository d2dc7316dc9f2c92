"""Monte Carlo campaigns: many runs of a scenario with dispersed config fields, as Ray tasks.

`spec` (the TOML spec and the per-run draws), `reach` (every dispersion can change what the runs
compute), `toml_writer` (each run's scenario file), `paths` (the campaign's folder, the runs'
results and their digests, resume), `one_run` (one run and its collected rows), `execute` (the
driver on Ray or in this process), `results` (campaign.parquet, campaign.duckdb), `report` and
`figures` (report.md, its figures, campaign.rrd), `landing` (a closed-loop campaign's
touchdowns), `sweep` (the paper's Table 1 as a campaign). The campaign sits above the stages (it
runs their plans with the one executor) and below the command line.
"""
