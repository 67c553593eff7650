"""A set of Gaussians in one local frame, as trainable parameters in 3DGS activations.

Parameters (per Gaussian, first dimension N): ``means`` [N, 3] (m, local frame), ``scales``
[N, 3] log of the standard deviations, ``quats`` [N, 4] (w, x, y, z, any norm), ``opacities``
[N] logits, ``sh0`` [N, 3] the degree-0 SH coefficient (colour = 0.5 + C0 * sh0) and, with a
``sh_degree`` above 0, ``shN`` [N, (degree + 1)^2 - 1, 3], and for a moving part with a learned
response to the light ``light_gain`` [N, 3] (colour x ``1 + light_gain . l``, ``l`` the unit
direction towards the light in the node's frame). Kept as a dict of
``torch.nn.Parameter`` so :class:`manisplat.splat.DefaultStrategy` can densify it.

View-dependent colour is evaluated on the view direction in the node's own frame: for a link or
an object seen by a fixed camera, that direction turns as the part turns, so the bands also
capture how the part's shading changes with its orientation under the scene's fixed lights; for
a camera that rides on the part (a wrist camera and its gripper's fingers) the direction hardly
turns, and ``light_gain`` is what follows the light as the arm turns the part under it.
"""

from __future__ import annotations

import math

import torch

from manisplat.scene.placement import activate
from manisplat.splat.sh import C0

LEARNING_RATES = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3, "shN": 2.5e-3 / 20,
                  "light_gain": 2.5e-3}


class GaussianSet:
    """Trainable Gaussians of one scene-graph node and their Adam optimizer.

    One optimizer holds every parameter (a group each, named like the parameter, fused
    updates); ``optimizers`` maps each parameter name to it, the form
    :class:`manisplat.splat.DefaultStrategy` expects.
    """

    def __init__(self, params: dict[str, torch.Tensor], *, scene_scale: float = 1.0, lr_scale: float = 1.0,
                 device: torch.device | str | None = None) -> None:
        self.params = {k: torch.nn.Parameter(v.detach().to(device).clone().float()) for k, v in params.items()}
        self.scene_scale = scene_scale
        lrs = dict(LEARNING_RATES)
        lrs["means"] *= scene_scale
        self.optimizer = torch.optim.Adam(
            [{"params": [p], "lr": lrs[k] * lr_scale, "name": k} for k, p in self.params.items()],
            eps=1e-15, fused=True,
        )
        self.optimizers = {k: self.optimizer for k in self.params}
        self.strategy_state: dict | None = None
        self.sh_degree = 0 if "shN" not in self.params else int(round((self.params["shN"].shape[1] + 1) ** 0.5)) - 1
        self.active_degree = 0  # bands in use (raised during training up to sh_degree)
        self._band_weights: tuple[tuple, torch.Tensor] | None = None  # band_weights()'s, for its key

    @classmethod
    def from_points(
        cls, points: torch.Tensor, colors: torch.Tensor, spacing: torch.Tensor | float, *,
        normals: torch.Tensor | None = None, opacity: float = 0.5, scene_scale: float = 1.0, sh_degree: int = 0,
    ) -> "GaussianSet":
        """Gaussians at ``points`` [N, 3] with RGB ``colors`` [N, 3] in [0, 1].

        ``spacing`` (m, scalar or [N]) is the distance to neighbouring points: the standard
        deviation starts at half of it. With ``normals`` [N, 3] the Gaussians start as flat discs
        in the surface (a tenth as thick), otherwise as spheres.
        """
        n = len(points)
        s = torch.as_tensor(spacing, dtype=torch.float32).expand(n).clamp_min(1e-4) * 0.5
        scales = s[:, None].repeat(1, 3)
        quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1)
        if normals is not None:
            scales[:, 2] = s * 0.1
            quats = _quats_aligning_z(normals.float())
        sh0 = (colors.float().clamp(0.02, 0.98) - 0.5) / C0
        params = {
            "means": points.float(),
            "scales": torch.log(scales),
            "quats": quats,
            "opacities": torch.full((n,), math.log(opacity / (1 - opacity))),
            "sh0": sh0,
        }
        if sh_degree > 0:
            params["shN"] = torch.zeros(n, (sh_degree + 1) ** 2 - 1, 3)
        return cls(params, scene_scale=scene_scale)

    def __len__(self) -> int:
        return len(self.params["means"])

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    def to(self, device: torch.device | str) -> "GaussianSet":
        """Move the parameters, their Adam moments and the densification statistics to
        ``device`` in place (new ``Parameter`` objects, registered with the optimizer); returns self."""
        device = torch.device(device)
        if self.device == device:
            return self
        if len(self.optimizer.param_groups) != len(self.params):
            raise ValueError("GaussianSet.to moves a set with its own optimizer; this one shares an optimizer "
                             "(move the sets before sharing it)")
        saved = self.optimizer.state_dict()
        self.params = {k: torch.nn.Parameter(v.detach().to(device)) for k, v in self.params.items()}
        self.use_optimizer(torch.optim.Adam(
            [{**{k: v for k, v in g.items() if k != "params"}, "params": [self.params[g["name"]]]}
             for g in self.optimizer.param_groups]))
        self.optimizer.load_state_dict(saved)  # moves the moments to the parameters' device
        if self.strategy_state is not None:
            self.strategy_state = {k: v.to(device) if isinstance(v, torch.Tensor) else v
                                   for k, v in self.strategy_state.items()}
        return self

    def learn_light_response(self) -> None:
        """Give every Gaussian a ``light_gain`` [N, 3], starting at 0 (colours as before), trained
        by the set's optimizer from now on. For a moving part: how its shading follows the light
        as the part turns under it."""
        if "light_gain" in self.params:
            return
        gain = torch.nn.Parameter(torch.zeros(len(self), 3, device=self.device))
        self.params["light_gain"] = gain
        self.optimizer.add_param_group({"params": [gain], "lr": LEARNING_RATES["light_gain"], "name": "light_gain"})
        self.optimizers["light_gain"] = self.optimizer

    def use_optimizer(self, optimizer: torch.optim.Optimizer) -> None:
        """Let ``optimizer`` (which must hold every parameter of this set, e.g. one optimizer
        shared by all nodes of a scene graph) update these parameters instead of the own one."""
        held = {id(p) for g in optimizer.param_groups for p in g["params"]}
        missing = [k for k, p in self.params.items() if id(p) not in held]
        if missing:
            raise ValueError(f"the optimizer does not hold parameters {missing}")
        self.optimizer = optimizer
        self.optimizers = {k: optimizer for k in self.params}

    def activated(self, camera_center: torch.Tensor | None = None,
                  light: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        """(means [N, 3], quats [N, 4], scales [N, 3], opacities [N], colours [N, 3]) for rendering.

        ``camera_center`` [3], in this node's frame, enables the view-dependent bands; ``light``
        [3], the unit direction towards the light in this node's frame, the response to it.
        """
        return activate(self.params, camera_center, self.band_weights(), light)

    def band_weights(self) -> torch.Tensor | None:
        """[K-1] float32 weights of the view-dependent coefficients ``shN`` on their device: 1 for
        the bands up to ``active_degree``, 0 above; None without ``shN``."""
        shN = self.params.get("shN")
        if shN is None:
            return None
        in_use = (self.active_degree + 1) ** 2 - 1
        key = (in_use, shN.shape[1], shN.device)
        if self._band_weights is None or self._band_weights[0] != key:
            weights = (torch.arange(shN.shape[1], device=shN.device) < in_use).float()
            self._band_weights = (key, weights)
        return self._band_weights[1]

    def step(self) -> None:
        """One optimizer step for every parameter, then clear the gradients."""
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def set_learning_rate(self, name: str, lr: float) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                group["lr"] = lr

    def ply_dict(self) -> dict[str, torch.Tensor]:
        """The raw parameters in the layout :func:`manisplat.splat.save_ply` writes."""
        p = self.params
        out = {"means": p["means"], "scales": p["scales"], "quats": p["quats"],
               "opacities": p["opacities"], "sh0": p["sh0"][:, None, :]}
        if "shN" in p:
            out["shN"] = p["shN"]
        return out


def _quats_aligning_z(normals: torch.Tensor) -> torch.Tensor:
    """Quaternions [N, 4] rotating the local z axis onto unit ``normals`` [N, 3] (shortest arc).

    For a normal opposite to z (n = -z) the half-way vector is undefined; a rotation by pi about x
    is used there.
    """
    n = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    z = torch.tensor([0.0, 0.0, 1.0]).expand_as(n)
    w = 1.0 + (z * n).sum(-1, keepdim=True)
    xyz = torch.linalg.cross(z, n, dim=-1)
    q = torch.cat([w, xyz], dim=-1)
    flipped = w[:, 0] < 1e-6
    q[flipped] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    return q / q.norm(dim=-1, keepdim=True)
