"""A slow, obviously correct twin of the renderer for tests.

Every Gaussian is evaluated at every pixel straight from the formulas of SPEC section 3 (no tiles,
no bounding boxes, no expanded polynomials), then composited one Gaussian at a time in depth
order. Float64 throughout. Only for small scenes. The conventions follow `RenderConventions`,
written here from the reference rasterizers' own formulas: 2DGS's `compute_aabb` point for the
low-pass centre, and diff-gaussian-rasterization's Jacobian clamp and tile rectangle for "ewa".
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from surfsplat import Cameras, Gaussians
from surfsplat.geometry.sh import sh_to_color
from surfsplat.render.types import RenderConventions


def reference_render(
    g: Gaussians,
    cameras: Cameras,
    width: int,
    height: int,
    mode: str = "surfel",
    near: float = 0.01,
    conventions: RenderConventions | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Un-normalized colour [C, 3, H, W], alpha [C, 1, H, W], depth [C, 1, H, W], normal [C, 3, H, W]."""
    rules = conventions or RenderConventions()
    dt = torch.float64
    outs = []
    for c in range(len(cameras)):
        w2c = cameras.w2c[c].to(dt)
        K = cameras.K[c].to(dt)
        R_cw, t_cw = w2c[:3, :3], w2c[:3, 3]
        means = g.means.to(dt)
        mu = means @ R_cw.T + t_cw
        Rw = g.rotations.to(dt)
        j = torch.arange(width, dtype=dt) + 0.5
        i = torch.arange(height, dtype=dt) + 0.5
        py, px = torch.meshgrid(i, j, indexing="ij")
        px, py = px.reshape(-1), py.reshape(-1)
        order = torch.argsort(mu[:, 2])
        color = torch.zeros(px.shape[0], 3, dtype=dt)
        normal = torch.zeros(px.shape[0], 3, dtype=dt)
        depth = torch.zeros(px.shape[0], dtype=dt)
        T = torch.ones(px.shape[0], dtype=dt)
        done = torch.zeros(px.shape[0], dtype=torch.bool)
        cam_center = cameras.centers[c].to(dt)
        for n in order.tolist():
            z_c = mu[n, 2]
            if z_c <= near:
                continue
            center = (K @ mu[n])[:2] / z_c
            if mode == "surfel":
                Rc = R_cw @ Rw[n]
                tu = Rc[:, 0] * g.scales[n, 0].to(dt)
                tv = Rc[:, 1] * g.scales[n, 1].to(dt)
                T_mat = K @ torch.stack((tu, tv, mu[n]), dim=1)
                if rules.lowpass_center_sigma is not None:  # 2DGS compute_aabb: t = (k^2, k^2, -1)
                    k2 = rules.lowpass_center_sigma**2
                    t = torch.tensor([k2, k2, -1.0], dtype=dt)
                    d = (t * T_mat[2] * T_mat[2]).sum()
                    if d < 0:
                        center = torch.stack(((t * T_mat[0] * T_mat[2]).sum(), (t * T_mat[1] * T_mat[2]).sum())) / d
                h_u = px[:, None] * T_mat[2] - T_mat[0]
                h_v = py[:, None] * T_mat[2] - T_mat[1]
                cr = torch.linalg.cross(h_u, h_v)
                u, v = cr[:, 0] / cr[:, 2], cr[:, 1] / cr[:, 2]
                rho3d = u * u + v * v
                rho2d = 2 * ((px - center[0]) ** 2 + (py - center[1]) ** 2)
                rho = torch.minimum(rho3d, rho2d)
                z = torch.where(rho3d <= rho2d, T_mat[2, 0] * u + T_mat[2, 1] * v + T_mat[2, 2], z_c)
            else:
                x, y = mu[n, 0] / z_c, mu[n, 1] / z_c
                fx, fy = K[0, 0], K[1, 1]
                if rules.ewa_jacobian_clamp is not None:  # 3DGS: limx = 1.3 tan(fovx / 2), tan = W / (2 fx)
                    lim_x = rules.ewa_jacobian_clamp * width / (2 * fx)
                    lim_y = rules.ewa_jacobian_clamp * height / (2 * fy)
                    x, y = x.clamp(-lim_x, lim_x), y.clamp(-lim_y, lim_y)
                J = torch.tensor([[fx / z_c, 0, -fx * x / z_c], [0, fy / z_c, -fy * y / z_c]], dtype=dt)
                cov2d = J @ R_cw @ g.covariances[n].to(dt) @ R_cw.T @ J.T + 0.3 * torch.eye(2, dtype=dt)
                d = torch.stack((px - center[0], py - center[1]), dim=-1)
                rho = (d @ torch.linalg.inv(cov2d) * d).sum(-1)
                if rules.ewa_support == "release":  # diff-gaussian-rasterization: getRect on 16-pixel blocks
                    a, b, c_ = cov2d[0, 0], cov2d[0, 1], cov2d[1, 1]
                    mid = 0.5 * (a + c_)
                    lam = mid + torch.sqrt(torch.clamp(mid * mid - (a * c_ - b * b), min=0.1))
                    radius = torch.ceil(3 * torch.sqrt(lam))
                    reach = torch.ones_like(px, dtype=torch.bool)
                    for p_img, pix, size in ((center[0] - 0.5, px, width), (center[1] - 0.5, py, height)):
                        grid = -(-size // 16)
                        lo = int(min(max(int(torch.floor((p_img - radius) / 16)), 0), grid))
                        hi = int(min(max(int(torch.floor((p_img + radius + 15) / 16)), 0), grid))
                        reach &= (pix >= 16 * lo) & (pix < 16 * hi)
                    rho = torch.where(reach, rho, torch.full_like(rho, torch.inf))
                z = torch.full_like(px, float(z_c))
            alpha = (g.opacities[n].to(dt) * torch.exp(-0.5 * rho)).clamp(max=0.99)
            alpha = torch.where(alpha >= 1 / 255, alpha, torch.zeros_like(alpha))
            next_T = T * (1 - alpha)
            stop = next_T < 1e-4
            take = ~done & ~stop & (alpha > 0)
            done |= ~done & stop & (alpha > 0)
            w = torch.where(take, alpha * T, torch.zeros_like(alpha))
            rgb = sh_to_color(g.sh[n].to(dt), F.normalize(means[n] - cam_center, dim=0))
            nrm = Rw[n][:, 2]
            if float(nrm @ (means[n] - cam_center)) > 0:
                nrm = -nrm
            color += w[:, None] * rgb
            normal += w[:, None] * nrm
            depth += w * z
            T = torch.where(take, next_T, T)
        outs.append((color, 1 - T, depth, normal))

    def img(x, ch):
        return torch.stack([o[x].reshape(height, width, ch) for o in outs]).permute(0, 3, 1, 2)

    color = img(0, 3)
    alpha = torch.stack([o[1].reshape(height, width) for o in outs])[:, None]
    depth = torch.stack([o[2].reshape(height, width) for o in outs])[:, None]
    return color, alpha, depth, img(3, 3)
