"""The one contract between the model and the renderer: Gaussians in the world frame."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

from ..utils.checks import SurfSplatInputError, check_tensor
from .rotations import quat_to_matrix
from .sh import sh_degree_from_bases

# Third scale of a surfel seen as a thin 3D Gaussian (how the release and 3DGS baselines render it).
THIN_SCALE = 1e-10


@dataclass
class Gaussians:
    """N Gaussian surfels (optionally with leading batch dims `...`), already activated.

    means:       [..., N, 3] world positions
    quats:       [..., N, 4] rotation (w, x, y, z); the surfel lies in the rotated x-y plane,
                 its normal is the rotated z axis
    scales:      [..., N, 2] standard deviations along the tangent axes u, v (world units)
    opacities:   [..., N]    in (0, 1)
    sh:          [..., N, 3, (d+1)^2] real SH per colour channel, d in 0..3
    explicit_covariances: [..., N, 3, 3] optional; when set, the EWA renderer uses it instead of
                 the surfel's own thin covariance (the release's quirky rotations are carried this way)
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    sh: Tensor
    explicit_covariances: Tensor | None = None
    validate: bool = True  # set False only for tensors already validated (internal use)

    def __post_init__(self) -> None:
        if not self.validate:
            return
        batch = tuple(self.means.shape[:-2]) if isinstance(self.means, Tensor) else ()
        lead: list[int | str | None] = [*batch, "N"]
        check_tensor("gaussians.means", self.means, (*lead, 3))
        check_tensor("gaussians.quats", self.quats, (*batch, self.means.shape[-2], 4))
        n = self.means.shape[-2]
        check_tensor("gaussians.scales", self.scales, (*batch, n, 2))
        check_tensor("gaussians.opacities", self.opacities, (*batch, n))
        check_tensor("gaussians.sh", self.sh, (*batch, n, 3, None))
        try:
            sh_degree_from_bases(self.sh.shape[-1])
        except ValueError as err:
            raise SurfSplatInputError(f"gaussians.{err}") from None
        if self.explicit_covariances is not None:
            check_tensor("gaussians.explicit_covariances", self.explicit_covariances, (*batch, n, 3, 3))
        if n > 0:
            qn = self.quats.norm(dim=-1)
            if bool((qn < 1e-12).any()):
                raise SurfSplatInputError("gaussians.quats: zero-norm quaternion")
            if bool((self.scales < 0).any()):
                raise SurfSplatInputError("gaussians.scales: negative scale")
            if bool(((self.opacities < 0) | (self.opacities > 1)).any()):
                raise SurfSplatInputError("gaussians.opacities: values outside [0, 1]")

    # ------------------------------------------------------------------ derived quantities
    def __len__(self) -> int:
        return self.means.shape[-2]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh.shape[-1])

    @property
    def rotations(self) -> Tensor:
        """[..., N, 3, 3] rotation matrices; columns are tangent u, tangent v, normal."""
        return quat_to_matrix(self.quats)

    @property
    def normals(self) -> Tensor:
        """[..., N, 3] unit surfel normals (the rotated z axis; sign not oriented)."""
        return self.rotations[..., :, 2]

    @property
    def covariances(self) -> Tensor:
        """[..., N, 3, 3] world covariance: the explicit one if given, else R diag(su^2, sv^2, eps^2) R^T."""
        if self.explicit_covariances is not None:
            return self.explicit_covariances
        R = self.rotations
        third = torch.full_like(self.scales[..., :1], THIN_SCALE)
        var = torch.cat((self.scales, third), dim=-1).square()
        return (R * var[..., None, :]) @ R.transpose(-1, -2)

    # ------------------------------------------------------------------ container helpers
    def _map(self, fn) -> Gaussians:
        values = {
            f.name: (fn(getattr(self, f.name)) if isinstance(getattr(self, f.name), Tensor) else getattr(self, f.name))
            for f in fields(self)
        }
        values["validate"] = False
        return Gaussians(**values)

    def to(self, *args, **kwargs) -> Gaussians:
        return self._map(lambda t: t.to(*args, **kwargs))

    def detach(self) -> Gaussians:
        return self._map(lambda t: t.detach())

    def clone(self) -> Gaussians:
        """Copies of every tensor (outside `torch.inference_mode`: tensors autograd may use again)."""
        return self._map(lambda t: t.clone())

    def select(self, index) -> Gaussians:
        """Index the leading batch dims, e.g. `g.select(0)` for the first scene of a batch."""
        return self._map(lambda t: t[index])

    def subset(self, mask_or_index: Tensor) -> Gaussians:
        """Keep a subset of the N Gaussians (unbatched only)."""
        if self.means.ndim != 2:
            raise SurfSplatInputError("subset: expected unbatched Gaussians ([N, 3] means)")
        return self._map(lambda t: t[mask_or_index])

    def with_explicit_covariances(self, covariances: Tensor | None) -> Gaussians:
        return replace(self, explicit_covariances=covariances, validate=False)

    @staticmethod
    def cat(items: list[Gaussians]) -> Gaussians:
        """Concatenate along the Gaussian axis N."""
        has_cov = [g.explicit_covariances is not None for g in items]
        if any(has_cov) and not all(has_cov):
            raise SurfSplatInputError("cat: either all or none of the inputs must carry explicit covariances")
        return Gaussians(
            means=torch.cat([g.means for g in items], dim=-2),
            quats=torch.cat([g.quats for g in items], dim=-2),
            scales=torch.cat([g.scales for g in items], dim=-2),
            opacities=torch.cat([g.opacities for g in items], dim=-1),
            sh=torch.cat([g.sh for g in items], dim=-3),
            explicit_covariances=torch.cat([g.explicit_covariances for g in items], dim=-3) if all(has_cov) else None,
            validate=False,
        )
