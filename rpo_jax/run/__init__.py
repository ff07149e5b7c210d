"""A training run on the host: its options and plan, the chunk loop, the run directory and its
files, checkpoints, metrics and summaries, evaluation, videos and population steps between
chunks, trackers, saved policies, and the library's way from Python to a run directory."""
