"""Image quality metrics: PSNR, SSIM (3DGS's Gaussian-window SSIM) and LPIPS when available.

Images are float tensors in [0, 1], ``[H, W, C]`` (one image) or ``[B, H, W, C]`` (a batch);
metrics are computed per image and returned as a 0-d tensor or a ``[B]`` tensor, on the
images' device. ``ssim`` is differentiable (the trainer uses ``1 - ssim`` as a loss).

LPIPS needs the ``lpips`` package (which imports torchvision) and its backbone weights
(torchvision's ImageNet models, downloaded into the torch hub cache on first use). When either
is missing, :func:`lpips_or_reason` returns ``(None, reason)``: never a substitute number.
"""
from __future__ import annotations

import functools
import importlib

import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2
LPIPS_NETS = ("alex", "vgg", "squeeze")


def _as_batch(img: torch.Tensor, gt: torch.Tensor, what: str) -> tuple[torch.Tensor,
                                                                       torch.Tensor, bool]:
    """Validate a pair of images; return them as [B, H, W, C] and whether input was batched."""
    if not isinstance(img, torch.Tensor) or not isinstance(gt, torch.Tensor):
        raise TypeError(f"{what}: img and gt must be torch tensors, got "
                        f"{type(img).__name__} and {type(gt).__name__}")
    if img.shape != gt.shape:
        raise ValueError(f"{what}: img {tuple(img.shape)} and gt {tuple(gt.shape)} differ in shape")
    if img.ndim not in (3, 4):
        raise ValueError(f"{what}: expected [H, W, C] or [B, H, W, C], got {tuple(img.shape)}")
    if not img.is_floating_point() or not gt.is_floating_point():
        raise TypeError(f"{what}: expected float images in [0, 1], got {img.dtype} and {gt.dtype}")
    batched = img.ndim == 4
    if not batched:
        img, gt = img.unsqueeze(0), gt.unsqueeze(0)
    return img, gt, batched


def psnr(img: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Peak signal-to-noise ratio per image, 20 log10(1 / sqrt(MSE)) for a peak of 1.

    img, gt: [H, W, C] or [B, H, W, C] in [0, 1]. mask (optional): [H, W], [H, W, 1], [B, H, W]
    or [B, H, W, 1], bool or float weights; the MSE is then the weighted mean over masked pixels
    and all channels. Returns [] or [B]; +inf for identical images.
    """
    x, y, batched = _as_batch(img, gt, "psnr")
    sq = (x - y).square()  # [B, H, W, C]
    if mask is None:
        mse = sq.mean(dim=(1, 2, 3))
    else:
        m = _mask_as_batch(mask, x.shape, batched).to(sq.dtype)  # [B, H, W, 1]
        weight = m.sum(dim=(1, 2, 3)) * x.shape[-1]
        if bool((weight <= 0).any()):
            raise ValueError("psnr: the mask selects no pixel in at least one image")
        mse = (sq * m).sum(dim=(1, 2, 3)) / weight
    out = -10.0 * torch.log10(mse)
    return out if batched else out[0]


def _mask_as_batch(mask: torch.Tensor, shape: torch.Size, batched: bool) -> torch.Tensor:
    b, h, w, _ = shape
    m = mask
    if m.ndim == (4 if batched else 3) and m.shape[-1] == 1:
        m = m[..., 0]
    if not batched:
        m = m.unsqueeze(0)
    if tuple(m.shape) != (b, h, w):
        raise ValueError(f"psnr: mask {tuple(mask.shape)} does not match images "
                         f"{tuple(shape if batched else shape[1:])}")
    return m.unsqueeze(-1)


@functools.lru_cache(maxsize=16)
def gaussian_window_1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA, *,
                       dtype: torch.dtype = torch.float32,
                       device: torch.device | str | None = None) -> torch.Tensor:
    """Normalised 1-D Gaussian taps [size], centred on size // 2 (the 3DGS SSIM window is the
    outer product of this with itself). Cached per (size, sigma, dtype, device): treat the
    result as read-only."""
    x = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-x.square() / (2.0 * sigma ** 2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def ssim_map(img: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Per-pixel, per-channel SSIM map as in 3DGS: 11x11 Gaussian window (sigma 1.5), C1 =
    0.01^2, C2 = 0.03^2, each channel separately, zero padding of window // 2 ('same' size).

    img, gt: [H, W, C] or [B, H, W, C]. Returns the same shape. Near the border (5 pixels) the
    zero padding biases local statistics, as in 3DGS; scikit-image instead crops that band.
    The compiled CPU kernel (baselines/ssim_kernel.py) where it can run (CPU, float32/float64,
    gt needing no gradient), else :func:`ssim_map_torch`.
    """
    from baselines import ssim_kernel  # a compiled library behind ctypes: loaded on first use

    x, y, batched = _as_batch(img, gt, "ssim")
    reason = ssim_kernel.unusable_reason(x, y)
    if reason is not None:
        ssim_kernel.log_fallback_once(reason)
        return ssim_map_torch(img, gt)
    g = gaussian_window_1d(dtype=x.dtype, device=x.device)
    out = ssim_kernel.ssim_map_kernel(x, y, g, SSIM_C1, SSIM_C2)
    return out if batched else out[0]


def ssim_map_torch(img: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """:func:`ssim_map` in torch (grouped separable convolutions): the oracle of the compiled
    kernel's tests and its fallback; differentiable with respect to both images."""
    x, y, batched = _as_batch(img, gt, "ssim")
    b, h, w, c = x.shape
    # channels-first; the five local moments go through one grouped, separable convolution
    x = x.permute(0, 3, 1, 2)
    y = y.permute(0, 3, 1, 2)
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # [B, 5C, H, W]
    g = gaussian_window_1d(dtype=x.dtype, device=x.device)
    pad = SSIM_WINDOW // 2
    k = 5 * c
    # separable filtering with zero padding equals 3DGS's 2-D conv2d(padding=window // 2)
    moments = F.conv2d(stack, g.view(1, 1, 1, -1).expand(k, 1, 1, SSIM_WINDOW),
                       padding=(0, pad), groups=k)
    moments = F.conv2d(moments, g.view(1, 1, -1, 1).expand(k, 1, SSIM_WINDOW, 1),
                       padding=(pad, 0), groups=k)
    mu_x, mu_y, e_xx, e_yy, e_xy = moments.split(c, dim=1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    var_x, var_y, cov = e_xx - mu_xx, e_yy - mu_yy, e_xy - mu_xy
    num = (2.0 * mu_xy + SSIM_C1) * (2.0 * cov + SSIM_C2)
    den = (mu_xx + mu_yy + SSIM_C1) * (var_x + var_y + SSIM_C2)
    out = (num / den).permute(0, 2, 3, 1)  # [B, H, W, C]
    return out if batched else out[0]


def ssim(img: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean of :func:`ssim_map` over pixels and channels, per image: [] or [B].
    Differentiable with respect to both inputs."""
    m = ssim_map(img, gt)
    return m.mean(dim=(-3, -2, -1))


class LpipsMetric:
    """LPIPS with lazy loading. Call it to get ``(value, None)`` or ``(None, reason)``.

    The ``lpips`` package is imported on first use; its network is built once per device
    (``verbose=False``). A failure (package missing, torchvision unusable, backbone weights not
    obtainable) is remembered and reported as the reason on every later call.
    """

    def __init__(self, net: str = "vgg"):
        if net not in LPIPS_NETS:
            raise ValueError(f"LpipsMetric: net must be one of {LPIPS_NETS}, got {net!r}")
        self.net = net
        self._models: dict[str, torch.nn.Module] = {}
        self._reason: str | None = None

    @property
    def reason(self) -> str | None:
        """Why LPIPS is unavailable (None when it worked or was not tried yet)."""
        return self._reason

    def _model(self, device: torch.device) -> torch.nn.Module | None:
        key = str(device)
        if key in self._models or self._reason is not None:
            return self._models.get(key)
        try:
            lpips = importlib.import_module("lpips")
        except ImportError as err:
            self._reason = (f"the lpips package is not installed ({err}); install the 'lpips' "
                            "extra on a machine whose torch build has a matching torchvision")
            return None
        except Exception as err:  # e.g. torchvision present but built for another torch
            self._reason = f"the lpips package failed to import: {type(err).__name__}: {err}"
            return None
        try:
            model = lpips.LPIPS(net=self.net, verbose=False)
        except Exception as err:  # weights missing and not downloadable, corrupt file, ...
            self._reason = (f"lpips could not build its '{self.net}' network: "
                            f"{type(err).__name__}: {err} (the backbone weights come from "
                            "torchvision's model zoo, cached under torch.hub.get_dir())")
            return None
        model = model.to(device).eval()
        for p in model.parameters():
            p.requires_grad_(False)
        self._models[key] = model
        return model

    def __call__(self, img: torch.Tensor, gt: torch.Tensor
                 ) -> tuple[torch.Tensor | None, str | None]:
        """img, gt: [H, W, 3] or [B, H, W, 3] in [0, 1]. Returns ([] or [B] tensor, None) or
        (None, reason)."""
        x, y, batched = _as_batch(img, gt, "lpips")
        if x.shape[-1] != 3:
            raise ValueError(f"lpips: expected 3 channels, got {x.shape[-1]}")
        model = self._model(x.device)
        if model is None:
            return None, self._reason
        with torch.no_grad():
            # lpips takes [B, 3, H, W]; normalize=True maps [0, 1] to its [-1, 1] input range
            d = model(x.permute(0, 3, 1, 2).float(), y.permute(0, 3, 1, 2).float(),
                      normalize=True)
        out = d.reshape(x.shape[0]).to(img.dtype)
        return (out if batched else out[0]), None


_LPIPS: dict[str, LpipsMetric] = {}


def lpips_or_reason(img: torch.Tensor, gt: torch.Tensor, net: str = "vgg"
                    ) -> tuple[torch.Tensor | None, str | None]:
    """LPIPS of img against gt with a shared :class:`LpipsMetric` per network:
    ``(value, None)`` or ``(None, reason)`` when LPIPS is unavailable."""
    metric = _LPIPS.get(net)
    if metric is None:
        metric = _LPIPS[net] = LpipsMetric(net)
    return metric(img, gt)

