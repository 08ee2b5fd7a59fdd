"""A program may import surfsplat inside `torch.inference_mode()`. Tensors made at import time
would then be inference tensors, which autograd refuses to save for backward: no module or class
of the package may hold one, and a differentiable use after such an import works."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

SCRIPT = r"""
import importlib, json, pkgutil, sys
import torch

with torch.inference_mode():
    import surfsplat

    names = [m.name for m in pkgutil.walk_packages(surfsplat.__path__, "surfsplat.")]
    failed = {}
    for name in names:
        if name.endswith("__main__"):  # runs the command line
            continue
        try:
            importlib.import_module(name)
        except ImportError as err:  # an optional extra that is not installed
            failed[name] = repr(err)
held = []
for name, module in list(sys.modules.items()):
    if not name.startswith("surfsplat"):
        continue
    for attr, value in vars(module).items():
        values = {attr: value}
        if isinstance(value, type) and value.__module__ == name:
            values.update({f"{attr}.{a}": v for a, v in vars(value).items()})
        held += [f"{name}.{a}" for a, v in values.items() if isinstance(v, torch.Tensor) and v.is_inference()]

# differentiable uses of the package's constants after that import
from surfsplat import Cameras
from surfsplat.geometry.sh_rotation import sh_rotation_matrix

c2w = torch.eye(4, dtype=torch.float64)[None].requires_grad_(True)
K = torch.tensor([[[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]]], dtype=torch.float64)
Cameras(c2w, K).to_opengl().sum().backward()
angle = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
R = torch.stack([torch.stack([angle.cos(), -angle.sin(), angle * 0]), torch.stack([angle.sin(), angle.cos(), angle * 0]),
                 torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)])
(sh_rotation_matrix(R[None], 2, convention="e3nn")[0, 4:, 4:] ** 2).sum().backward()
assert angle.grad is not None
print(json.dumps({"modules": len(names), "failed": failed, "held": held, "grads": [float(c2w.grad.abs().sum()), float(angle.grad)]}))
"""


def test_importing_under_inference_mode_leaves_no_inference_tensor_behind():
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["modules"] > 50 and result["failed"] == {}, result
    assert result["held"] == [], result["held"]
    assert result["grads"][0] > 0 and result["grads"][1] == result["grads"][1], result  # autograd ran
