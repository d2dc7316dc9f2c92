"""Files and databases: workspace paths, run folders and atomic commits, the catalogue
database, table column conventions, read-only SQL."""
