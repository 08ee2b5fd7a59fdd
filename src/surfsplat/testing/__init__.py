"""Tools for testing code that runs on accelerators, usable without one (like `torch.testing`).

`standin_device`: a stand-in accelerator for CPU-only machines that catches tensors created on the
wrong device and records every host synchronisation (used by the test suite and
`benchmarks/host_syncs.py`).

`gsplat_reference`: gsplat's own pure-PyTorch reference of 2DGS and 3DGS rasterization, runnable on
a CPU (needs the pinned gsplat of the test extra), with the seeded scenes the renderer is held to.
"""
