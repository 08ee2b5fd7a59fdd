"""Tools for testing code that runs on accelerators, usable without one (like `torch.testing`).

`standin_device`: a stand-in accelerator for CPU-only machines that catches tensors created on the
wrong device and records every host synchronisation (used by the test suite and
`benchmarks/host_syncs.py`).

`gsplat_reference`: gsplat's own pure-PyTorch reference of 2DGS and 3DGS rasterization, runnable on
a CPU (needs the pinned gsplat of the test extra), with the seeded scenes the renderer is held to.

`lenses`: realistic calibrations of every COLMAP camera model; `lens_capture`: pinhole photos with known
cameras written as a camera with a lens would have taken them (photos, a COLMAP model, nerfstudio's and
instant-ngp's transforms.json), for `tests/data/make_distorted.py` and `benchmarks/undistort.py`.
"""
