"""ReFlow as a plugin of the 4DGS host: canonical space construction, static/dynamic separated
deformation and self-correction flow matching. Only the ReFlow parts live here; everything it
builds on is in `baselines`."""
