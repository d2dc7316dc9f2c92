"""Pure numerical core: numpy/scipy (and healpy) only, no files, databases, logging or Rerun."""
