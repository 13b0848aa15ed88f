"""Bi-Mapper (Li et al., RA-L 2023): dual-stream BEV semantic mapping network.

``BiMapper(config, rig, grid)`` (config: :class:`~.config.BiMapperConfig`) holds both streams, the fusion and the BEV decoder:

* GV (:mod:`.gv`): EfficientNet + neck per camera, per-camera two-layer MLP to the ego BEV
  feature map, views summed; a 1x1 head gives GV's foreground logit for mutual learning.
* LV (:mod:`.lv`): IPM of each input onto its camera plane, U-Net (per-class logits for the
  Across-Space Loss), features merged into the ego feature grid with the extrinsics.
* Fusion ``gv_weight * F_g + lv_weight * F_l`` (paper best: 1.0 / 0.1) or ``concat``; stream
  ablations ``gv`` / ``lv`` / ``both``.
* Decoder: two 3x3 convs at the feature resolution, then x2 bilinear upsampling + conv stages
  (channels halved, at least 16) until the next doubling would overshoot, a final resize to
  the grid and a 3x3 conv + 1x1 head to per-class logits ``(C, H, W)``. The paper only says
  "the BEV decoder likes [HDMapNet]"; this is a plain conv/upsampling decoder (no ResNet).

Inputs are raw camera images in rig order and are resized inside :meth:`BiMapper.preprocess`
to the model input size: width ``input_width``, height from the camera's aspect via
``CameraModel.scaled`` (the same factor rescales the intrinsics for the IPM tables). Default
112 px wide: surround6 (400x225) -> 112x63, cam2bev4 (482x302) -> 112x70.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.labels.classes import NUM_LABELS, label_lut, resolve_classes
from bev_mapper_core.nn.config import rgb_stats
from bev_mapper_core.nn.decoder import BevDecoder
from bev_mapper_core.nn.efficientnet import downsampled_size
from bev_mapper_core.nn.inputs import preprocess_images
from bev_mapper_core.nn.prior_skip import PRIOR_LOGIT_SCALE, PriorProjection, check_prior

from .config import FUSIONS, STREAMS, BiMapperConfig
from .geometry import BiMapperGeometry
from .gv import CamEncoder, GVTransform
from .lv import LVStream


class BiMapper(nn.Module):
    """The Bi-Mapper network for one rig (camera order and calibration) and BEV grid.

    Calibration tables are non-persistent buffers rebuilt by :meth:`set_rig`; they are never
    saved with the weights.
    """

    def __init__(self, config: BiMapperConfig, rig: Rig, grid: BevGrid) -> None:
        super().__init__()
        self.config, self.rig, self.grid = config, rig, grid
        self.num_cameras = len(rig.cameras)
        self.num_classes = len(config.classes)
        geo = BiMapperGeometry(rig, grid, config.input_width, config.plane_spec(), config.bev_downsample,
                               any_aspect=config.streams in ("lv", "none"))
        self.input_size = geo.input_size
        self.feat_hw = geo.feat_grid.shape
        for name, arr in geo.arrays().items():
            self.register_buffer(name, torch.from_numpy(np.ascontiguousarray(arr)), persistent=False)
        Cb = config.bev_channels
        cin = config.in_channels
        self.use_gv = config.streams in ("gv", "both")
        self.use_lv = config.streams in ("lv", "both")
        if self.use_gv:
            self.cam_encoder = CamEncoder(config.encoder_config(cin), config.neck_channels, Cb)
            s = self.cam_encoder.stride
            fv_hw = (downsampled_size(self.input_size[0], s), downsampled_size(self.input_size[1], s))
            self.gv = GVTransform(self.num_cameras, fv_hw, self.feat_hw, config.gv_hidden)
            self.gv_fg_head = nn.Conv2d(Cb, 1, 1)
        if self.use_lv:
            interp = "nearest" if config.input_kind == "labels" else "bilinear"
            self.lv = LVStream(config.encoder_config(cin), config.unet_channels, Cb, self.num_classes, interp)
        dec_in = 2 * Cb if (config.fusion == "concat" and config.streams == "both") else Cb
        self.raw_hw = self._raw_hw(geo, rig)
        # the decoder head's skip input: ipm_skip: averaged input + coverage; prior_skip: segipm's K
        # class probabilities + coverage
        self.prior_channels = cin + 1 if config.ipm_skip else self.num_classes + 1 if config.prior_skip else 0
        self.decoder = BevDecoder(dec_in, config.decoder_channels, self.num_classes, self.feat_hw, grid.shape,
                                  skip_channels=self.prior_channels, visibility_head=config.visibility_head,
                                  min_channels=config.decoder_min_channels)
        if config.ipm_skip:
            self.ipm_proj = nn.Conv2d(self.prior_channels, self.num_classes, 1)
            with torch.no_grad():
                self.ipm_proj.weight.zero_()
                self.ipm_proj.bias.zero_()
                if config.input_kind == "labels":
                    # logits start as IPM's: +4 where the averaged class indicator is 1, -4 at 0
                    lut = torch.from_numpy(label_lut(resolve_classes(config.classes)).astype(np.float32))  # (L, K)
                    self.ipm_proj.weight[:, :NUM_LABELS, 0, 0] = PRIOR_LOGIT_SCALE * lut.t()
                    self.ipm_proj.bias.fill_(-PRIOR_LOGIT_SCALE / 2)
        if config.prior_skip:
            self.prior_proj = PriorProjection(self.num_classes)  # logits start as segipm's: 8 p - 4 per class
        mean, std = rgb_stats(config.encoder_config(3).lite)  # a Lite encoder reads ImageNet-Lite's scaling
        self.register_buffer("rgb_mean", torch.tensor(mean).view(1, 1, 3, 1, 1), persistent=False)
        self.register_buffer("rgb_std", torch.tensor(std).view(1, 1, 3, 1, 1), persistent=False)

    # ------------------------------------------------------------ calibration
    def _raw_hw(self, geo: BiMapperGeometry, rig: Rig) -> tuple[int, int] | None:
        """``(H, W)`` shared by all cameras' delivered images (None if they differ).

        Raises:
            ConfigError: sizes differ, but lv_full_res needs the images batched.
        """
        sizes = set(geo.raw_sizes)
        if len(sizes) != 1:
            if self.config.lv_full_res:
                raise ConfigError(f"lv_full_res batches the camera-size images: rig {rig.name!r} has "
                                  f"cameras of different sizes {sorted(sizes)}")
            return None  # the IPM prior then gathers from each camera's own image (a list)
        w, h = sizes.pop()
        return (h, w)

    @property
    def rig_free(self) -> bool:
        """No parameter depends on the cameras: without the GV stream (per-camera MLPs sized by
        the camera count and input size) every camera runs the same LV U-Net and the geometry is
        all in the tables, so the model maps any rig (:meth:`set_rig` takes any cameras).
        """
        return not self.use_gv

    def geometry(self, rig: Rig) -> BiMapperGeometry:
        """The calibration tables of ``rig`` for this model's configuration (for :meth:`set_rig`)."""
        return BiMapperGeometry(rig, self.grid, self.config.input_width, self.config.plane_spec(),
                                self.config.bev_downsample, any_aspect=self.rig_free)

    def set_rig(self, rig: Rig, geometry: BiMapperGeometry | None = None) -> None:
        """Rebuild the calibration tables for a new calibration of the same cameras; a
        :attr:`rig_free` model takes any rig (other cameras, counts and image sizes).
        ``geometry``: ``rig``'s tables from :meth:`geometry`, when the caller keeps them.

        Raises:
            ConfigError: different camera names/order, or a different model input size (a
                model with the GV stream).
        """
        if not self.rig_free and rig.names != self.rig.names:
            raise ConfigError(f"rig cameras {list(rig.names)} differ from the model's {list(self.rig.names)}")
        geo = geometry if geometry is not None else self.geometry(rig)
        if not self.rig_free and geo.input_size != self.input_size:
            raise ConfigError(f"new calibration gives input size {geo.input_size}, the model needs {self.input_size}")
        raw_hw = self._raw_hw(geo, rig)
        dev = self.rgb_mean.device
        for name, arr in geo.arrays().items():
            t = torch.from_numpy(np.ascontiguousarray(arr))
            old = getattr(self, name)
            if old.shape == t.shape:
                old.copy_(t)
            else:  # a rig-free model on other cameras: new table shapes (a copy: the caller may keep ``geometry``)
                self.register_buffer(name, t.to(dev, copy=True), persistent=False)
        self.rig, self.raw_hw = rig, raw_hw
        self.num_cameras, self.input_size = len(rig.cameras), geo.input_size

    def tables(self) -> dict[str, torch.Tensor]:
        """The calibration tables as tensors (on the model's device)."""
        return {n: getattr(self, n) for n in ("ipm_grid", "ipm_valid", "gt_grid", "gt_valid", "merge_grid", "merge_weight", "frustum")}

    def ipm_prior(self, images: torch.Tensor | list[torch.Tensor], cam_mask: torch.Tensor | None = None) -> torch.Tensor:
        """The ``ipm_skip`` input: camera-size images IPM'd onto the full ego grid.

        Exactly the classical :class:`~bev_mapper_core.methods.ipm.mapper.IpmMapper`'s geometry (a gather
        through ``prior_index``, nearest pixel) and its averaging over the cameras that see a
        cell, without its occlusion reasoning (``ipm_occlusion``): the shipped weights were
        trained on this prior.

        Args:
            images: raw images as for :meth:`preprocess`, at the cameras' delivered size; for
                cameras of different sizes a list of N tensors ``(B, H_n, W_n[, 3])`` in rig order.
            cam_mask: (B, N) cameras present, None = all.

        Returns:
            (B, C_in + 1, H, W): labels: the average one-hot label of the covering cameras;
            rgb: their average normalised colour; last channel 1 where some camera covers.
        """
        if isinstance(images, (list, tuple)):
            return self._ipm_prior_each(images, cam_mask)
        if images.shape[1] != self.num_cameras or tuple(images.shape[2:4]) != self.raw_hw:
            raise ValueError(f"images {tuple(images.shape)} do not match {self.num_cameras} cameras of "
                             f"{self.raw_hw} (H, W) from the calibration")
        return self._prior(images, cam_mask)

    def _prior(self, images: torch.Tensor, cam_mask: torch.Tensor | None) -> torch.Tensor:
        """:meth:`ipm_prior` of checked images ``(B, N, H, W[, 3])`` (any H, W the index fits)."""
        dev = self.rgb_mean.device
        idx = self.prior_index  # (N, Hg*Wg)
        B, N = images.shape[:2]
        Hg, Wg = self.grid.shape
        HW = Hg * Wg
        valid = self.frustum.flatten(1)[None].to(torch.float32).expand(B, N, HW)  # (N, Hg, Wg) -> (B, N, HW)
        if cam_mask is not None:
            valid = valid * cam_mask.to(dev).to(torch.float32)[:, :, None]
        count = valid.sum(1)  # (B, HW)
        if self.config.input_kind == "labels":
            if images.dim() != 4:
                raise ValueError(f"label images must be (B, N, H, W), got {tuple(images.shape)}")
            ids = images.to(dev).reshape(B, N, -1)  # (B, N, H, W) -> (B, N, H*W)
            g = torch.gather(ids, 2, idx[None].expand(B, N, HW)).long()  # (B, N, HW)
            g = torch.where((g >= 0) & (g < NUM_LABELS), g, torch.zeros_like(g))
            slot = torch.arange(HW, device=dev)[None, None] * NUM_LABELS + g  # (B, N, HW) into (HW, L)
            acc = torch.zeros(B, HW * NUM_LABELS, device=dev)
            acc.scatter_add_(1, slot.reshape(B, -1), valid.reshape(B, -1))
            acc = acc.view(B, HW, NUM_LABELS)  # (B, HW*L) -> (B, HW, L)
        else:
            if images.dim() != 5 or images.shape[-1] != 3:
                raise ValueError(f"RGB images must be (B, N, H, W, 3), got {tuple(images.shape)}")
            x = images.to(dev).reshape(B, N, -1, 3).float() / 255.0  # (B, N, H, W, 3) -> (B, N, H*W, 3)
            x = (x - self.rgb_mean.view(1, 1, 1, 3)) / self.rgb_std.view(1, 1, 1, 3)
            g = torch.gather(x, 2, idx[None, :, :, None].expand(B, N, HW, 3))  # (B, N, HW, 3)
            acc = (g * valid[..., None]).sum(1)  # (B, HW, 3)
        avg = acc / count.clamp(min=1.0)[..., None]
        prior = torch.cat([avg, (count > 0).to(avg.dtype)[..., None]], dim=2)  # (B, HW, C_in + 1)
        return prior.permute(0, 2, 1).reshape(B, -1, Hg, Wg)  # (B, HW, P) -> (B, P, Hg, Wg)

    def _ipm_prior_each(self, images: list[torch.Tensor], cam_mask: torch.Tensor | None) -> torch.Tensor:
        """:meth:`ipm_prior` of cameras of different sizes: each camera's own image flattened and
        padded to the largest, then gathered as one batch (the indices never reach the padding).
        """
        sizes = [tuple(int(v) for v in (c.model.image_size[1], c.model.image_size[0])) for c in self.rig.cameras]
        if len(images) != self.num_cameras or any(tuple(im.shape[1:3]) != hw for im, hw in zip(images, sizes)):
            raise ValueError(f"images {[tuple(im.shape) for im in images]} do not match the {self.num_cameras} "
                             f"cameras' sizes {sizes} (H, W) from the calibration")
        longest = max(h * w for h, w in sizes)
        flat = []
        for im in images:
            f = im.reshape(im.shape[0], -1, *im.shape[3:])  # (B, H_n, W_n[, 3]) -> (B, H_n*W_n[, 3])
            pad = longest - f.shape[1]
            if pad:
                f = torch.cat([f, f.new_zeros(f.shape[0], pad, *f.shape[2:])], dim=1)
            flat.append(f)
        x = torch.stack(flat, dim=1)  # (B, N, L[, 3])
        x = x[:, :, None]  # (B, N, L[, 3]) -> (B, N, 1, L[, 3]): one row, the same flat indices
        return self._prior(x, cam_mask)

    # ---------------------------------------------------------- preprocessing
    def preprocess(self, images: torch.Tensor, resize: bool = True) -> torch.Tensor:
        """Raw camera images (rig order) -> model input (B, N, C_in, h, w) float at ``input_size``.

        Args:
            images: labels: (B, N, H, W) integer label ids (ids >= NUM_LABELS count as
                unlabeled), resized nearest, then one-hot; rgb: (B, N, H, W, 3) uint8 or float
                in [0, 255], resized bilinearly (antialiased), scaled to [0, 1], normalised.
            resize: False keeps the images' own size (the LV stream's full-resolution input).
        """
        size = self.input_size if resize else tuple(images.shape[2:4])
        return preprocess_images(images, self.config.input_kind, size, self.rgb_mean, self.rgb_std)

    # ---------------------------------------------------------------- forward
    def forward(self, images: torch.Tensor, cam_mask: torch.Tensor | None = None,
                prior: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Raw images (B, N, H, W[, 3]) at the cameras' size -> outputs (see :meth:`forward_preprocessed`);
        ``prior``: a ``prior_skip`` model's segipm prior ``(B, K + 1, H, W)`` (an ``ipm_skip`` model
        computes its own).
        """
        x_lv = None
        if self.config.lv_full_res and self.use_lv:
            x_lv = self.preprocess(images, resize=False)  # (B, N, C_in, H, W) at camera size
        if self.config.ipm_skip:
            prior = self.ipm_prior(images, cam_mask)
        return self.forward_preprocessed(self.preprocess(images), cam_mask, x_lv, prior)

    def forward_preprocessed(self, x: torch.Tensor, cam_mask: torch.Tensor | None = None,
                             x_lv: torch.Tensor | None = None, prior: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Run the network on model inputs.

        Args:
            x: (B, N, C_in, h, w) from :meth:`preprocess`.
            cam_mask: (B, N) bool, cameras present (absent ones are ignored); None = all.
            x_lv: optional (B, N, C_in, H, W) input of the LV stream at any resolution (the IPM
                tables are normalised coordinates, so they apply at every size); None = ``x``.
            prior: (B, C_in + 1, H, W) from :meth:`ipm_prior`, required by ``ipm_skip`` models;
                (B, K + 1, H, W) segipm's map (:class:`~bev_mapper_core.methods.segipm.prior.SegIpmPrior`),
                required by ``prior_skip`` models.

        Returns dict:
            ``logits`` (B, K, H, W) fused per-class logits on the full grid;
            ``gv_feat`` / ``lv_feat`` (B, C, hb, wb) stream features (None if disabled);
            ``gv_fg_logits`` / ``lv_fg_logits`` (B, 1, hb, wb) foreground logits for mutual
            learning; ``lv_plane_logits`` (B, N, K, Hp, Wp); ``lv_coverage`` (B, 1, hb, wb);
            ``visibility_logits`` (B, 1, H, W) the visibility head's logit (None without it);
            ``cam_mask`` (B, N) bool; ``gt_grid`` (N, Hp, Wp, 2) / ``gt_valid`` (N, Hp, Wp) the
            ASL target tables.
        """
        B, N = x.shape[:2]
        if N != self.num_cameras or tuple(x.shape[-2:]) != tuple(self.input_size):
            raise ValueError(f"input {tuple(x.shape)} does not match {N}=={self.num_cameras} cameras at {self.input_size}")
        if cam_mask is None:
            cam_mask = torch.ones(B, N, dtype=torch.bool, device=x.device)
        cam_mask = cam_mask.to(x.device).bool()
        x = x * cam_mask[:, :, None, None, None].to(x.dtype)
        out: dict[str, torch.Tensor | None] = {
            "gv_feat": None, "lv_feat": None, "gv_fg_logits": None, "lv_fg_logits": None,
            "lv_plane_logits": None, "lv_coverage": None, "cam_mask": cam_mask,
            "gt_grid": self.gt_grid, "gt_valid": self.gt_valid,
        }
        if self.use_gv:
            f = self.cam_encoder(x.flatten(0, 1))  # (B*N, C_in, h, w) -> (B*N, C, hf, wf)
            f = f.view(B, N, *f.shape[1:])  # (B*N, C, hf, wf) -> (B, N, C, hf, wf)
            out["gv_feat"] = self.gv(f, cam_mask)
            out["gv_fg_logits"] = self.gv_fg_head(out["gv_feat"])
        if self.use_lv:
            if x_lv is None:
                x_lv = x
            else:
                x_lv = x_lv * cam_mask[:, :, None, None, None].to(x_lv.dtype)
            lv = self.lv(x_lv, self.tables(), cam_mask)
            out.update(lv_feat=lv["feat"], lv_fg_logits=lv["fg_logits"], lv_plane_logits=lv["plane_logits"], lv_coverage=lv["coverage"])
        cfg = self.config
        if cfg.streams == "gv":
            fused = out["gv_feat"]
        elif cfg.streams == "lv":
            fused = out["lv_feat"]
        elif cfg.streams == "none":  # ablation control: the decoder gets no image evidence
            fused = x.new_zeros(B, cfg.bev_channels, *self.feat_hw)
        elif cfg.fusion == "concat":
            fused = torch.cat([out["gv_feat"], out["lv_feat"]], dim=1)  # (B, 2C, hb, wb)
        else:
            fused = cfg.gv_weight * out["gv_feat"] + cfg.lv_weight * out["lv_feat"]
        if cfg.ipm_skip:
            if prior is None:
                raise ValueError("an ipm_skip model needs the IPM prior: call forward() with the camera-size images")
            logits, vis = self.decoder(fused, prior)
            out["logits"] = logits + self.ipm_proj(prior)
        elif cfg.prior_skip:
            check_prior(prior, self.prior_channels, self.grid.shape)
            prior = prior.to(fused.dtype)
            logits, vis = self.decoder(fused, prior)
            out["logits"] = logits + self.prior_proj(prior)
        else:
            out["logits"], vis = self.decoder(fused)
        out["visibility_logits"] = vis
        return out

    def calibrated(self, logits: torch.Tensor) -> torch.Tensor:
        """Class logits (B, K, H, W) divided by the per-class ``config.temperature`` (unchanged
        when the model is not calibrated).
        """
        t = self.config.temperature
        if t is None:
            return logits
        return logits / torch.tensor(t, dtype=logits.dtype, device=logits.device).view(1, -1, 1, 1)

    def known(self, cam_mask: torch.Tensor | None = None) -> torch.Tensor:
        """(B, H, W) bool: grid cells on the ground inside at least one present camera's image."""
        fr = self.frustum  # (N, H, W)
        if cam_mask is None:
            return fr.any(0)[None]
        return (fr[None] & cam_mask.bool()[:, :, None, None].to(fr.device)).any(1)  # (B, N, H, W) -> (B, H, W)


def build_bimapper(rig: Rig, grid: BevGrid | None = None, **overrides) -> BiMapper:
    """Convenience: ``BiMapper(BiMapperConfig(**overrides), rig, grid or BevGrid())``."""
    return BiMapper(BiMapperConfig(**overrides), rig, grid or BevGrid())


__all__ = ["FUSIONS", "STREAMS", "BevDecoder", "BiMapper", "BiMapperConfig", "build_bimapper"]
