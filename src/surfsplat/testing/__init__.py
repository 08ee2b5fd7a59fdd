"""Tools for testing code that runs on accelerators, usable without one (like `torch.testing`).

`standin_device`: a stand-in accelerator for CPU-only machines that catches tensors created on the
wrong device and records every host synchronisation (used by the test suite and
`benchmarks/host_syncs.py`).
"""
