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
from torch.nn import functional as F

from ..classes import NUM_LABELS
from ..errors import ConfigError
from ..grid import BevGrid
from ..rig import Rig
from .config import FUSIONS, RGB_MEAN, RGB_STD, STREAMS, BiMapperConfig
from .efficientnet import downsampled_size
from .geometry import BiMapperGeometry
from .gv import CamEncoder, GVTransform, conv_bn_relu
from .lv import LVStream

class BevDecoder(nn.Module):
    """Conv + upsampling decoder from the BEV feature map to per-class logits on the full grid."""

    def __init__(self, cin: int, channels: int, num_classes: int, in_hw: tuple[int, int], out_hw: tuple[int, int]) -> None:
        super().__init__()
        self.out_hw = tuple(out_hw)
        self.stem = nn.Sequential(conv_bn_relu(cin, channels), conv_bn_relu(channels, channels))
        ups = []
        h, w = in_hw
        c = channels
        while h * 2 <= out_hw[0] and w * 2 <= out_hw[1]:
            ups.append(conv_bn_relu(c, max(16, c // 2)))
            c = max(16, c // 2)
            h, w = h * 2, w * 2
        self.ups = nn.ModuleList(ups)
        self.head = nn.Sequential(conv_bn_relu(c, c), nn.Conv2d(c, num_classes, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` (B, cin, h, w) -> logits (B, classes, H, W)."""
        x = self.stem(x)
        for up in self.ups:
            x = up(F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False))
        if tuple(x.shape[-2:]) != self.out_hw:
            x = F.interpolate(x, size=self.out_hw, mode="bilinear", align_corners=False)
        return self.head(x)


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
        geo = BiMapperGeometry(rig, grid, config.input_width, config.plane_spec(), config.bev_downsample)
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
        self.decoder = BevDecoder(dec_in, config.decoder_channels, self.num_classes, self.feat_hw, grid.shape)
        self.register_buffer("rgb_mean", torch.tensor(RGB_MEAN).view(1, 1, 3, 1, 1), persistent=False)
        self.register_buffer("rgb_std", torch.tensor(RGB_STD).view(1, 1, 3, 1, 1), persistent=False)

    # ------------------------------------------------------------ calibration
    def set_rig(self, rig: Rig) -> None:
        """Rebuild the calibration tables for a new calibration of the same cameras.

        Raises:
            ConfigError: different camera names/order, or a different model input size.
        """
        if rig.names != self.rig.names:
            raise ConfigError(f"rig cameras {list(rig.names)} differ from the model's {list(self.rig.names)}")
        geo = BiMapperGeometry(rig, self.grid, self.config.input_width, self.config.plane_spec(), self.config.bev_downsample)
        if geo.input_size != self.input_size:
            raise ConfigError(f"new calibration gives input size {geo.input_size}, the model needs {self.input_size}")
        for name, arr in geo.arrays().items():
            getattr(self, name).copy_(torch.from_numpy(np.ascontiguousarray(arr)))
        self.rig = rig

    def tables(self) -> dict[str, torch.Tensor]:
        """The calibration tables as tensors (on the model's device)."""
        return {n: getattr(self, n) for n in ("ipm_grid", "ipm_valid", "gt_grid", "gt_valid", "merge_grid", "merge_weight", "frustum")}

    # ---------------------------------------------------------- preprocessing
    def preprocess(self, images: torch.Tensor, resize: bool = True) -> torch.Tensor:
        """Raw camera images (rig order) -> model input (B, N, C_in, h, w) float at ``input_size``.

        Args:
            images: labels: (B, N, H, W) integer label ids (ids >= NUM_LABELS count as
                unlabeled), resized nearest, then one-hot; rgb: (B, N, H, W, 3) uint8 or float
                in [0, 255], resized bilinearly (antialiased), scaled to [0, 1], normalised.
            resize: False keeps the images' own size (the LV stream's full-resolution input).
        """
        h, w = self.input_size if resize else tuple(images.shape[2:4])
        dev = self.rgb_mean.device
        if self.config.input_kind == "labels":
            if images.dim() != 4:
                raise ValueError(f"label images must be (B, N, H, W), got {tuple(images.shape)}")
            B, N, H, W = images.shape
            ids = images.to(dev)
            if (H, W) != (h, w):
                ids = F.interpolate(ids.reshape(B * N, 1, H, W).float(), size=(h, w), mode="nearest-exact")  # (B*N, 1, h, w)
                ids = ids.view(B, N, h, w)  # (B*N, 1, h, w) -> (B, N, h, w)
            ids = ids.long()
            ids = torch.where((ids >= 0) & (ids < NUM_LABELS), ids, torch.zeros_like(ids))
            return F.one_hot(ids, NUM_LABELS).permute(0, 1, 4, 2, 3).float()  # (B, N, h, w, L) -> (B, N, L, h, w)
        if images.dim() != 5 or images.shape[-1] != 3:
            raise ValueError(f"RGB images must be (B, N, H, W, 3), got {tuple(images.shape)}")
        B, N, H, W, _ = images.shape
        x = images.to(dev).float().permute(0, 1, 4, 2, 3).reshape(B * N, 3, H, W) / 255.0  # -> (B*N, 3, H, W)
        if (H, W) != (h, w):
            x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
        x = x.view(B, N, 3, h, w)  # (B*N, 3, h, w) -> (B, N, 3, h, w)
        return (x - self.rgb_mean) / self.rgb_std

    # ---------------------------------------------------------------- forward
    def forward(self, images: torch.Tensor, cam_mask: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Raw images -> outputs (see :meth:`forward_preprocessed`)."""
        x_lv = None
        if self.config.lv_full_res and self.use_lv:
            x_lv = self.preprocess(images, resize=False)  # (B, N, C_in, H, W) at camera size
        return self.forward_preprocessed(self.preprocess(images), cam_mask, x_lv)

    def forward_preprocessed(self, x: torch.Tensor, cam_mask: torch.Tensor | None = None,
                             x_lv: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Run the network on model inputs.

        Args:
            x: (B, N, C_in, h, w) from :meth:`preprocess`.
            cam_mask: (B, N) bool, cameras present (absent ones are ignored); None = all.
            x_lv: optional (B, N, C_in, H, W) input of the LV stream at any resolution (the IPM
                tables are normalised coordinates, so they apply at every size); None = ``x``.

        Returns dict:
            ``logits`` (B, K, H, W) fused per-class logits on the full grid;
            ``gv_feat`` / ``lv_feat`` (B, C, hb, wb) stream features (None if disabled);
            ``gv_fg_logits`` / ``lv_fg_logits`` (B, 1, hb, wb) foreground logits for mutual
            learning; ``lv_plane_logits`` (B, N, K, Hp, Wp); ``lv_coverage`` (B, 1, hb, wb);
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
        elif cfg.fusion == "concat":
            fused = torch.cat([out["gv_feat"], out["lv_feat"]], dim=1)  # (B, 2C, hb, wb)
        else:
            fused = cfg.gv_weight * out["gv_feat"] + cfg.lv_weight * out["lv_feat"]
        out["logits"] = self.decoder(fused)
        return out

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
