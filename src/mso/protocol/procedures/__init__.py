"""Each distributed procedure as its own state machine (see :mod:`.base`)."""
