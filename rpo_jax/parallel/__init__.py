"""Where runs train: their placement on the devices of a machine (`devices`), and the processes
of a run over several hosts (`cluster`)."""
