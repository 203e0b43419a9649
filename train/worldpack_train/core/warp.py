"""The depth warp the geometry model is conditioned on: a stored frame, with
its depth, splatted into the target camera.

Each source pixel lands on the target pixel nearest to its projection
(floor(x + 0.5)) behind a z-buffer; ties go to the earlier pixel in row-major
order. A pixel with depth 0 saw nothing within range (sky): it is warped as a
direction at infinity (rotation only) and loses to every surface. Target
pixels nothing lands on are holes: 0 in the [-1, 1] image and 0 in the mask.

The Rust runtime has the same warp (`model::warp`); export writes reference
cases and a Rust test checks the two agree. Float64 throughout, so the two
round the same way."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .recipe import perturb_poses

DEPTH_UNIT_M = 1e-3  # depth maps are millimetres along the optical axis
SKY_KEY = 1e12  # z-buffer key of a direction at infinity (plus its pixel index)


def forward_warp(rgb: torch.Tensor, depth_mm: torch.Tensor, intrinsics: dict, src_c2w: torch.Tensor,
                 dst_c2w: torch.Tensor, present: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """K stored frames per item warped into the item's target camera behind
    one z-buffer: rgb (B, K, H, W, 3) uint8, depth_mm (B, K, H, W) integer,
    src_c2w (B, K, 4, 4), dst_c2w (B, 4, 4), OpenCV axes; `present` (B, K)
    bool leaves padding frames out. (B, H, W, 3) / (B, H, W) inputs and
    (B, 4, 4) source poses are one frame per item. Ties go to the earlier
    frame, then the earlier pixel, as a scan in that order with a strict `<`.
    Returns the warped image (B, H, W, 3) uint8 (0 in holes) and the mask
    (B, H, W) bool of pixels something landed on."""
    if rgb.dim() == 4:
        rgb, depth_mm, src_c2w = rgb[:, None], depth_mm[:, None], src_c2w[:, None]
    b, k, h, w, _ = rgb.shape
    dev = rgb.device
    if present is None:
        present = torch.ones(b, k, dtype=torch.bool, device=dev)
    fx, fy, cx, cy, near = (float(intrinsics[n]) for n in ("fx", "fy", "cx", "cy", "near"))
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64, device=dev),
                          torch.arange(w, dtype=torch.float64, device=dev), indexing="ij")
    d = depth_mm.to(torch.float64) * DEPTH_UNIT_M
    sky = depth_mm == 0
    ray = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], dim=-1)  # (H, W, 3), z = 1
    rs, ts = src_c2w[..., :3, :3].to(torch.float64), src_c2w[..., :3, 3].to(torch.float64)
    rd, td = dst_c2w[:, :3, :3].to(torch.float64), dst_c2w[:, :3, 3].to(torch.float64)
    # A surface point: camera -> world -> target camera. A sky direction: rotation only.
    turned = torch.einsum("bkij,hwj->bkhwi", rs, ray)
    world = turned * d[..., None] + ts[:, :, None, None, :]
    surface = torch.einsum("bji,bkhwj->bkhwi", rd, world - td[:, None, None, None, :])
    direction = torch.einsum("bji,bkhwj->bkhwi", rd, turned)
    q = torch.where(sky[..., None], direction, surface)
    z = q[..., 2]
    ahead = torch.where(sky, z > 1e-9, z > near)
    zs = torch.where(ahead, z, torch.ones_like(z))
    x = torch.floor(fx * q[..., 0] / zs + cx + 0.5)
    y = torch.floor(fy * q[..., 1] / zs + cy + 0.5)
    ok = ahead & (x >= 0) & (y >= 0) & (x < w) & (y < h) & present[:, :, None, None]
    pixel = torch.arange(h * w, dtype=torch.float64, device=dev).view(1, 1, h, w).expand(b, k, h, w)
    scan = torch.arange(k, dtype=torch.float64, device=dev).view(1, k, 1, 1) * (h * w) + pixel  # scan order
    key = torch.where(sky, SKY_KEY + pixel, z)
    target = (torch.arange(b, device=dev).view(b, 1, 1, 1) * (h * w) + y.clamp(0, h - 1).long() * w + x.clamp(0, w - 1).long())
    j, kk, idx = target[ok], key[ok], scan[ok]
    best = torch.full((b * h * w,), float("inf"), dtype=torch.float64, device=dev).scatter_reduce(0, j, kk, "amin")
    nearest = kk == best[j]
    first = torch.full((b * h * w,), float("inf"), dtype=torch.float64, device=dev)
    first = first.scatter_reduce(0, j[nearest], idx[nearest], "amin")
    win = nearest & (idx == first[j])
    out = torch.zeros(b * h * w, 3, dtype=torch.uint8, device=dev)
    out[j[win]] = rgb[ok][win]
    mask = torch.zeros(b * h * w, dtype=torch.bool, device=dev)
    mask[j[win]] = True
    return out.view(b, h, w, 3), mask.view(b, h, w)


def warp_input(encoder, scale: float, warped: torch.Tensor, mask: torch.Tensor, downsample: int) -> torch.Tensor:
    """What the denoiser's `warp` input holds, (B, C + 1, h, w): the encoded
    warped image (holes 0 in [-1, 1], scaled like every latent) and the share
    of each latent cell's pixels the warp covers."""
    image = (warped.to(torch.float32) / 127.5 - 1.0).permute(0, 3, 1, 2) * mask[:, None].to(torch.float32)
    latent = encoder(image) * scale
    cover = F.avg_pool2d(mask[:, None].to(torch.float32), downsample)
    return torch.cat([latent, cover], dim=1)


@torch.no_grad()
def batch_warp_pixels(source, batch, device: torch.device, pose_noise=None, noisy_items=None):
    """A training batch's warp in pixels: the warped image (B, H, W, 3,
    uint8) and where it landed (B, H, W, bool). Rows without a source frame
    get an empty warp. `pose_noise` (translation sd in blocks, rotation sd in
    degrees, a torch generator): the source frames' poses are perturbed as
    the recipe perturbs context poses, so the model learns how far to trust a
    warp made from a wrong pose. `noisy_items` (B,): which items get it
    (default: all)."""
    rgb, depth, src_pose, dst_pose, present = source.warp_pixels(batch)
    t = lambda a: torch.from_numpy(a).to(device)
    src = t(src_pose)
    if pose_noise is not None:
        b, k = src.shape[:2]
        which = t(present).float() * (noisy_items[:, None] if noisy_items is not None else 1.0)
        rows = perturb_poses(src[..., :3, :].reshape(b, k, 12).float(), which, *pose_noise).double()
        src = src.clone()
        src[..., :3, :] = rows.view(b, k, 3, 4)
    return forward_warp(t(rgb), t(depth), source.intrinsics, src, t(dst_pose), t(present))


@torch.no_grad()
def batch_warp(source, batch, autoencoder, device: torch.device, pose_noise=None, noisy_items=None) -> torch.Tensor:
    """The `warp` input for a training batch of `data.PlannedLatents`
    (`batch_warp_pixels`, encoded by `warp_input`)."""
    warped, mask = batch_warp_pixels(source, batch, device, pose_noise, noisy_items)
    return warp_input(autoencoder.encoder, autoencoder.scale, warped, mask, autoencoder.cfg.downsample)
