"""OpenMP's defaults for the command line, set before torch (and its OpenMP runtime) loads.

`OMP_WAIT_POLICY=PASSIVE`: the threads of torch's and the compiled kernels' OpenMP runtimes sleep between
parallel regions instead of spinning. GNU OpenMP's default spins each idle thread for a while after every
region, and the fit runs thousands of short regions with Python in between, so the spinning thread burns
a core for nothing: a 600-step fern fit on 2 cores took 56.9 CPU s spinning and 49.3 sleeping, in the same
wall time and to the same bits (benchmarks/openmp.py). A value the user set wins. Imported first by
`surfsplat.cli`; the library itself leaves the process's environment alone.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
