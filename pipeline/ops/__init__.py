"""Operations: typed functions that take tables and component options and return tables.

No run store, no RunConfig, no files: stages (and campaigns, the sweep among them) call them.
"""
