"""One stage's trainable module: the model with that stage's nets trainable and its loss (``forward(batch)``)."""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from genre_backend.geometry.spherical import crop_sph, hull_ramp, pad_sph
from genre_backend.nets.model import GenRe, save_model

from .burst import REFERENCE_SPEED, Speed
from .losses import depth_gradient_loss, depth_mse, outline_loss, sph_loss, voxel_loss
from .normals import NormalsHead, depth_normals, normals_loss

__all__ = ["BASELINE_STAGES", "StageModule", "hull_trimmed"]

BASELINE_STAGES = ("completion", "onestep")
RAMP_EPS = 1e-4  # the hull ramp's 0 and 1 as logits: ±9.2


def hull_trimmed(logits: torch.Tensor, sph: torch.Tensor, geometry, grad_width: float = 1.0) -> torch.Tensor:
    """The refiner's logits (B, 1, N, N, N) capped by the hull of the full maps (B, H, H) it read, as the mesh
    option ``sph_hull_carve`` caps its probabilities (``min(p, ramp)`` is ``sigmoid(min(logit, logit(ramp)))``);
    differentiable with respect to both, so the voxel loss also teaches the inpainting net where its map cuts the
    object.  The mesh option's ramp is one voxel wide, so only voxels within half a voxel of the hull pass a
    gradient to the map.  ``grad_width`` > 1 keeps the values and takes the cap's gradient from a ramp that many
    voxels wide instead (straight through), at the one-voxel ramp's mid slope (4 logits a voxel), so a map that cuts
    the object deeper also learns to open."""
    ramp = hull_ramp(sph, geometry).clamp(RAMP_EPS, 1.0 - RAMP_EPS)
    cap = torch.log(ramp) - torch.log1p(-ramp)
    if grad_width != 1.0:
        wide = hull_ramp(sph, geometry, grad_width)
        cap = cap.detach() + 4.0 * grad_width * (wide - wide.detach())
    return torch.minimum(logits, cap)


class StageModule(nn.Module):
    """The model with one stage's trainable parts; ``forward(batch)`` returns (loss, logged terms)."""

    def __init__(self, model: GenRe, stage: str, surface_weight: float, sph_loss: str = "mse", depth_weight: float = 0.0,
                 sph_teacher: float = 0.0, depth_dropout: float = 0.0, depth_gradient_weight: float = 0.0,
                 outline_weight: float = 0.0, speed: Speed = REFERENCE_SPEED, hull_grad_width: float = 1.0,
                 depth_lr_scale: float = 1.0, normals_weight: float = 0.0, depth_offset_weight: float = 1.0):
        super().__init__()
        # bf16 autocast per net as ``speed`` says (the nets' memory format is burst.apply_speed's); the losses in fp32
        self.speed = speed
        self.model, self.stage, self.surface_weight, self.sph_loss_kind = model, stage, surface_weight, sph_loss
        self.depth_weight = depth_weight  # the joint stage: the depth net's own loss, added with this weight
        self.depth_gradient_weight = depth_gradient_weight  # the depth loss's gradient matching term
        self.depth_offset_weight = depth_offset_weight  # the depth MSE's offset part counts this many times (losses.depth_mse)
        self.hull_grad_width = hull_grad_width  # the trim's gradient ramp (hull_trimmed), for weights storing sph_hull_carve
        self.outline_weight = outline_weight  # refine, joint: the grid's silhouette through the camera (losses.outline_loss)
        if outline_weight > 0 and stage not in ("refine", "joint"):
            raise ValueError(f"outline_weight: only the refine and joint stages train GenRe's grid (stage {stage!r})")
        if sph_teacher > 0 and stage != "refine":
            raise ValueError(f"sph_teacher: only the refine stage feeds the true map (stage {stage!r})")
        if depth_dropout > 0 and stage not in ("refine", "joint"):
            raise ValueError(f"depth_dropout: only the refine and joint stages have depth voxels to empty (stage {stage!r})")
        if depth_lr_scale != 1.0 and stage != "joint":
            raise ValueError(f"depth_lr_scale: only the joint stage trains the depth net with the others (stage {stage!r})")
        if depth_lr_scale == 0 and depth_weight > 0:
            raise ValueError("depth_weight: the depth net is frozen (depth_lr_scale 0); set depth_weight to 0")
        self.depth_lr_scale = depth_lr_scale  # the joint stage: the depth net's share of the learning rate
        if normals_weight > 0 and stage != "depth":
            raise ValueError(f"normals_weight: only the depth stage trains the depth net's normals head (stage {stage!r})")
        # the depth stage: a training-only normals head on the depth net's encoder (training.learn.normals); its
        # loss counts in training steps only, so validation losses compare with runs without it
        self.normals_weight = normals_weight
        self.aux = nn.ModuleDict()
        if normals_weight > 0:
            net = model.config.network
            self.aux["normals"] = NormalsHead(net.depth_widths, net.depth_decoder_blocks)
        # training batches only (StepBatches' per-sample "coin"): validation and inference see every input as it is
        self.sph_teacher, self.depth_dropout = sph_teacher, depth_dropout
        self.baseline = None
        if stage in BASELINE_STAGES:
            from .baselines import CompletionBaseline, OneStepNet

            self.baseline = (CompletionBaseline if stage == "completion" else OneStepNet)(model.config)
            if stage == "completion":  # the depth net it completes from: GenRe's (from --init), frozen
                self.baseline.depth_net.load_state_dict(model.depth_net.state_dict())
                # the completion net has the refiner's architecture and starts where GenRe's refiner
                # is: freshly initialised after the depth stage, or trained when continuing from full
                # weights, so that the two voxel nets always start level
                self.baseline.completion.load_state_dict(model.refiner.state_dict())
        trainable = {"depth": [model.depth_net], "inpaint": [model.inpaint_net], "refine": [model.refiner], "joint": [model],
                     "completion": [], "onestep": []}[stage]
        for p in model.parameters():
            p.requires_grad_(False)
        for part in trainable:
            for p in part.parameters():
                p.requires_grad_(True)
        if depth_lr_scale == 0:
            model.depth_net.requires_grad_(False)
        self.frozen = [m for m in (model.depth_net, model.inpaint_net, model.refiner) if not any(p.requires_grad for p in m.parameters())]
        if stage == "completion":
            for p in self.baseline.depth_net.parameters():
                p.requires_grad_(False)
            self.frozen.append(self.baseline.depth_net)

    def param_groups(self, weight_decay: float = 0.0) -> list[dict]:
        """The optimiser's parameter groups: every trainable parameter in one, or, where the depth net trains at
        its own share of the rate (``depth_lr_scale``), the depth net's in a second group with that ``lr_scale``.
        With ``weight_decay`` > 0 each group splits in two: the weights of convolutions and linear maps (more than
        one dimension) decay at that rate, biases and batch-norm scales (one dimension) do not."""
        depth = {id(p) for p in self.model.depth_net.parameters()}
        trainable = [p for p in self.parameters() if p.requires_grad]
        if self.depth_lr_scale in (0.0, 1.0):
            groups = [{"params": trainable}]
        else:
            groups = [{"params": [p for p in trainable if id(p) not in depth], "lr_scale": 1.0},
                      {"params": [p for p in trainable if id(p) in depth], "lr_scale": self.depth_lr_scale}]
        if weight_decay == 0:
            return groups
        return [{**group, "params": [p for p in group["params"] if (p.dim() > 1) == decays],
                 "weight_decay": weight_decay if decays else 0.0}
                for group in groups for decays in (True, False)]

    def checkpointed(self) -> tuple[str, nn.Module]:
        """The key prefix and module a checkpoint keeps: GenRe's nets, or for a baseline stage the
        baseline alone (so its checkpoint does not depend on GenRe's architecture)."""
        return ("model", self.model) if self.baseline is None else ("baseline", self.baseline)

    def save_weights(self, path: Path, extra: dict) -> None:
        """The stage's weights file: GenRe's format, or the baseline's for a baseline stage."""
        if self.baseline is None:
            save_model(self.model, path, extra)
        else:
            from .baselines import save_baseline

            save_baseline(self.baseline, path, extra)

    def train(self, mode: bool = True):
        super().train(mode)
        for m in self.frozen:
            m.eval()  # frozen nets keep their batch-norm statistics
        return self

    # ---- losses -------------------------------------------------------------------------
    def depth_loss(self, out, batch):
        valid = batch["depth"] > 0
        scale = self.model.config.network.depth_output_scale
        l_depth = depth_mse(out["depth"] * scale, batch["depth"] * scale, valid, self.depth_offset_weight)
        l_sil = F.binary_cross_entropy_with_logits(out["silhouette_logits"], batch["mask"].float())
        terms = {"depth_mse": l_depth, "silhouette_bce": l_sil}
        loss = l_depth + l_sil
        if self.depth_gradient_weight > 0:
            l_grad = depth_gradient_loss(out["depth"] * scale, batch["depth"] * scale, valid)
            terms["depth_gradient_l1"] = l_grad
            loss = loss + self.depth_gradient_weight * l_grad
        return loss, terms

    def depth_with_normals(self, batch):
        """The depth loss plus ``normals_weight`` times the normals head's (:mod:`training.learn.normals`)."""
        net = self.model.depth_net
        with self.speed.autocast("depth", batch["rgb"].device):
            skips, deep = net.encode(batch["rgb"])
            out = net.decode(skips, deep)
            normals = self.aux["normals"](skips, deep)
        loss, terms = self.depth_loss({k: v.float() for k, v in out.items()}, batch)
        true, valid = depth_normals(batch["depth"], self.model.config.camera)
        terms["normals_cos"] = normals_loss(normals.float(), true, valid)
        return loss + self.normals_weight * terms["normals_cos"], terms

    def sph_loss(self, parts: dict[str, torch.Tensor], batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """:func:`training.learn.losses.sph_loss` of the inpainting net's ``parts`` against ``batch["full_sph"]``."""
        return sph_loss(parts, batch["full_sph"], self.model.config.geometry, self.sph_loss_kind)

    def map_loss(self, parts: dict[str, torch.Tensor], batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The joint stage's spherical loss: :meth:`sph_loss` over the samples whose refiner read the net's map, as a
        mean over every sample in which the true-map samples (``batch["true_map"]``, TrainConfig.true_map) count 0;
        its logged terms are those samples' own means (with none: zero, the nets still reached)."""
        if "true_map" not in batch:
            return self.sph_loss(parts, batch)
        scored = ~batch["true_map"].bool()
        if not bool(scored.any()):
            loss, terms = self.sph_loss(parts, batch)
            return 0.0 * loss, {k: 0.0 * v for k, v in terms.items()}
        if bool(scored.all()):
            return self.sph_loss(parts, batch)
        loss, terms = self.sph_loss({k: v[scored] for k, v in parts.items()}, {"full_sph": batch["full_sph"][scored]})
        return loss * scored.float().mean(), terms

    def voxel_loss(self, logits, batch):
        """:func:`training.learn.losses.voxel_loss` of the refiner's logits against ``batch["voxels"]``."""
        return voxel_loss(logits, batch["voxels"], self.surface_weight)

    def _net(self, name: str, net, x: torch.Tensor):
        """``net(x)`` under the bf16 autocast ``self.speed`` gives ``name``; its tensors back in fp32."""
        with self.speed.autocast(name, x.device):
            out = net(x)
        return {k: v.float() for k, v in out.items()} if isinstance(out, dict) else out.float()

    def forward(self, batch: dict[str, torch.Tensor]):
        m = self.model
        if self.stage == "depth" and "normals" in self.aux and self.training:
            return self.depth_with_normals(batch)
        if self.stage == "depth":
            return self.depth_loss(self._net("depth", m.depth_net, batch["rgb"]), batch)
        if self.stage == "onestep":
            pad = m.config.geometry.sph_pad
            return self.sph_loss({"map": pad_sph(self.baseline(batch["rgb"])[:, None], pad)}, batch)
        if self.stage == "completion":
            b = self.baseline
            with torch.no_grad():
                depth = m.masked_depth(b.depth_net(batch["rgb"])["depth"], batch["mask"])
                vox_depth = b.depth_voxels(depth)
            return self.voxel_loss(b.complete(vox_depth), batch)
        with torch.set_grad_enabled(self.stage == "joint" and torch.is_grad_enabled()):
            depth_out = self._net("depth", m.depth_net, batch["rgb"])
            depth = m.masked_depth(depth_out["depth"], batch["mask"])
            partial = m.partial_sph(depth)
        pad = m.config.geometry.sph_pad
        if self.stage == "inpaint":
            return self.sph_loss(self._net("inpaint", m.inpaint_net.forward_parts, pad_sph(partial[:, None], pad)), batch)
        # the joint stage's depth-only samples (TrainConfig.depth_only) train the depth net's own loss alone: the map and
        # the grid are made and scored for the other samples only
        rest, rest_weight = batch, 1.0
        if self.stage == "joint" and "depth_only" in batch:
            kept = ~batch["depth_only"].bool()
            if not bool(kept.any()):  # the nets still run (every rank's gradients cover every parameter), weighted 0
                rest_weight = 0.0
            elif not bool(kept.all()):
                rest = {k: v[kept] for k, v in batch.items()}
                depth, partial = depth[kept], partial[kept]
        with torch.set_grad_enabled(self.stage == "joint" and torch.is_grad_enabled()):
            sph_parts = self._net("inpaint", m.inpaint_net.forward_parts, pad_sph(partial[:, None], pad))
            full = crop_sph(sph_parts["map"], pad)[:, 0]
            if self.training and "coin" in rest and self.sph_teacher > 0:
                full = torch.where((rest["coin"][:, 0] < self.sph_teacher)[:, None, None], rest["full_sph"], full)
            if self.stage == "joint" and "true_map" in rest:  # TrainConfig.true_map: the refiner reads the true map
                full = torch.where(rest["true_map"].bool()[:, None, None], rest["full_sph"], full)
            vox_sph, vox_depth = m.sph_voxels(full), m.depth_voxels(depth)
        if self.training and "coin" in rest and self.depth_dropout > 0:
            keep = (rest["coin"][:, 1] >= self.depth_dropout).to(vox_depth.dtype)
            vox_depth = vox_depth * keep.view(-1, *([1] * (vox_depth.dim() - 1)))
        logits = self._net("refiner", m.refiner, torch.cat([vox_sph, vox_depth], dim=1))
        if m.config.geometry.sph_hull_carve:  # trained as the weights are used: trimmed to the map's hull
            logits = hull_trimmed(logits, full, m.config.geometry, self.hull_grad_width)
        loss, terms = self.voxel_loss(logits, rest)
        if self.outline_weight > 0:
            terms["outline_bce"] = outline_loss(logits, rest["voxels"], m.config.camera)
            loss = loss + self.outline_weight * terms["outline_bce"]
        if self.stage == "joint":
            l_sph, sph_terms = self.map_loss(sph_parts, rest)
            terms.update(sph_terms)
            loss = rest_weight * (loss + l_sph)
            if self.depth_weight > 0:
                l_depth, depth_terms = self.depth_loss(depth_out, batch)
                terms.update(depth_terms)
                loss = loss + self.depth_weight * l_depth
        return loss, terms
