"""Operations: typed functions that take tables and component options and return tables.

No run store, no RunConfig, no files: stages (and the sweep, and campaigns) call them.
"""
