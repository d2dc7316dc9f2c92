"""Project errors: contract violations that name the file, row and field at fault."""


class PipelineError(Exception):
    """Base class of the errors the CLI reports as a clear one-line message (no traceback)."""


class ConfigError(PipelineError):
    """A scenario file or option is invalid (unknown key, wrong type, out of range)."""


class CatalogueError(PipelineError):
    """A catalogue file cannot be ingested (missing column, too many bad rows, unreadable)."""


class StageInputError(PipelineError):
    """A stage's upstream output is missing or does not match what the stage needs."""


class TableSchemaError(PipelineError):
    """A table a stage writes does not match its declared schema (`pipeline.vocab.tables`)."""
