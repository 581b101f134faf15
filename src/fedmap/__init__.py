"""fedmap: federated multi-agent mapping for planetary exploration."""

import os

__version__ = "0.1.0"

#: How long an OpenMP thread of torch's runtime (GNU libgomp) spins at a barrier before it
#: sleeps, set before torch is first imported unless the user set it. libgomp's default
#: spins 300,000 times: beside two busy processes on 2 cores a thread whose partner was
#: descheduled spun through its time slices, and ``fedmap demo`` took 4.9x its idle time
#: (126 s against 26 s, CPU time 46 -> 122 s). At 10,000 it took 2.3x (a fair share of the
#: cores predicts 2x) and 1.04x its idle time alone; OMP_WAIT_POLICY=PASSIVE gave 2.3x but
#: 1.17x idle (``python benchmarks/demo_load.py``).
GOMP_SPINCOUNT = "10000"
os.environ.setdefault("GOMP_SPINCOUNT", GOMP_SPINCOUNT)
