"""Plumbing every stage may use: atomic file writes (:mod:`.atomic`), worker threads
(:mod:`.threads`), input checks with clear errors (:mod:`.validate`) and mosaics of
patches for figures and layers (:mod:`.mosaic`). Imports no stage."""
