"""`python -m rpo_jax.report`: tables, statistics and figures from runs and experiments."""

import sys

from rpo_jax.report.compose import main

sys.exit(main())
