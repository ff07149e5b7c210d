"""Reports of runs and experiments (`python -m rpo_jax.report`): `compose` reads results and runs
and writes report.md, from `tables`, `figures`, `statistics` (intervals, IQM, probability of
improvement), `reference` (a published run to compare with) and `populations` (PBT's members)."""
