"""The persistent backend of a run and its shared services (see docs and :mod:`.contributor`)."""
