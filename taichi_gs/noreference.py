"""Image measures that need no sharp ground truth, for real captures.

- :func:`gradient_energy`: mean squared image gradient of the grey image (Rec. 601 luma) after a
  Gaussian of sigma 1 px (which damps pixel-level sensor noise and JPEG ringing, so noise does not
  pass for detail), derivatives by the Sobel operator normalised to per-pixel differences (/8),
  over the image less a 5-pixel border. A ramp of slope a grey levels per pixel scores a^2.
  Deblurring raises it; the ratio sharp render / blurred input is the "sharpness gain".
- :func:`laplacian_variance`: variance of the Laplacian (3 x 3) of the grey image, no pre-filter:
  the finest scales, where motion blur takes energy away first. Along a 7-Scenes slice it jumps
  between neighbouring frames with hand shake (4.5e-3 to 24e-3 two frames apart), where the
  sigma-1 gradient energy follows the scene content and hardly separates blurred from sharp
  neighbours. Noise raises it too, but frames next to each other share their noise level.
- :func:`sharpest_holdout`: the real-data test split. The sequence is cut into consecutive windows
  of ``every`` frames and the frame of highest Laplacian variance in each window is held out, so the
  test views are about as many as with "every n-th frame", spread over the whole sequence, and each
  is the least blurred frame near its place: the closest thing to sharp ground truth a real capture
  has. As with "every n-th frame", each held-out frame lies between two training frames: never the
  first or last frame, never next to another held-out frame (two in a row would leave a gap of three
  frames in training, and each test view one frame further from a training view on one side).
- :func:`warp_to_view`: a neighbouring frame's colour resampled into a test view through the test
  view's own depth and the two camera poses; the "blurred neighbour" floor that renders of a held-out
  frame must beat.
- :func:`dark_hole_fraction`: share of pixels where a render is dark although the input has colour.
"""

from __future__ import annotations

import cv2
import numpy as np
from skimage.metrics import structural_similarity

from .evaluate import psnr

BORDER = 5  # pixels left out of the gradient energy (Gaussian radius 4 + Sobel radius 1)


def grey(image: np.ndarray) -> np.ndarray:
    """Rec. 601 luma of an (H, W, 3) RGB image in [0, 1] (float64); (H, W) images pass through."""
    image = np.asarray(image, np.float64)
    return image if image.ndim == 2 else image[..., :3] @ np.array([0.299, 0.587, 0.114])


def gradient_energy(image: np.ndarray, sigma: float = 1.0, mask: np.ndarray | None = None) -> float:
    """Mean of |grad|^2 (grey levels per pixel, squared) after a Gaussian of ``sigma`` px; with a
    boolean ``mask`` (H, W), only over pixels at least ``BORDER`` px inside it."""
    g = grey(image)
    if sigma > 0:
        g = cv2.GaussianBlur(g, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    gx = cv2.Sobel(g, cv2.CV_64F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(g, cv2.CV_64F, 0, 1, ksize=3) / 8.0
    energy = (gx**2 + gy**2)[BORDER:-BORDER, BORDER:-BORDER]
    if mask is not None:
        energy = energy[eroded(mask, BORDER)[BORDER:-BORDER, BORDER:-BORDER]]
    return float(energy.mean()) if energy.size else 0.0


def eroded(mask: np.ndarray, radius: int) -> np.ndarray:
    """``mask`` less every pixel within ``radius`` (square) of a False pixel; the image's own edges
    do not erode it."""
    return cv2.erode(mask.astype(np.uint8), np.ones((2 * radius + 1,) * 2, np.uint8),
                     borderType=cv2.BORDER_CONSTANT, borderValue=1).astype(bool)


def laplacian_variance(image: np.ndarray) -> float:
    """Variance of the 3 x 3 Laplacian of the grey image (grey levels in [0, 1]) over the whole image."""
    return float(cv2.Laplacian(grey(image), cv2.CV_64F, ksize=1).var())


def sharpest_holdout(sharpness: np.ndarray | list[float], every: int) -> tuple[list[int], list[int]]:
    """(train, test) indices: in each window of ``every`` consecutive frames the sharpest frame that has
    training frames on both sides is a test view (ties go to the earlier frame). Windows are taken in
    order: a frame next to the previous window's test view, and the sequence's first and last frames,
    are not candidates, and a window without candidates holds nothing out. A last window shorter than
    ``every`` joins the one before it. ``every`` 0 holds nothing out."""
    sharpness = np.asarray(sharpness, dtype=np.float64)
    n = len(sharpness)
    if every <= 0:
        return list(range(n)), []
    if every < 2:
        raise ValueError(f"every must be 0 or at least 2, got {every}")
    starts = list(range(0, n, every))
    if len(starts) > 1 and n - starts[-1] < every:
        starts.pop()
    test: list[int] = []
    for start, end in zip(starts, [*starts[1:], n]):
        first = max(start, 1, test[-1] + 2 if test else 0)  # candidates: first .. stop - 1
        stop = min(end, n - 1)
        if first < stop:
            test.append(first + int(np.argmax(sharpness[first:stop])))
    held = set(test)
    return [i for i in range(n) if i not in held], test


def warp_to_view(source: np.ndarray, source_pose: np.ndarray, depth: np.ndarray, pose: np.ndarray,
                 K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``source`` (H, W, C) seen from camera ``pose``: each pixel with depth > 0 in ``depth`` (the
    target view's, metres) is back-projected, moved into the source camera (4x4 camera-to-world poses,
    OpenCV ``K`` shared by both) and sampled bilinearly. Returns (warped image, valid mask)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = depth.astype(np.float64)
    points = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)
    relative = np.linalg.inv(source_pose) @ pose
    moved = points @ relative[:3, :3].T + relative[:3, 3]
    zs = moved[..., 2]
    in_front = zs > 1e-6
    safe = np.where(in_front, zs, 1.0)
    map_x = (K[0, 0] * moved[..., 0] / safe + K[0, 2]).astype(np.float32)
    map_y = (K[1, 1] * moved[..., 1] / safe + K[1, 2]).astype(np.float32)
    warped = cv2.remap(np.asarray(source, np.float32), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    valid = (z > 0) & in_front & (map_x >= 0) & (map_x <= w - 1) & (map_y >= 0) & (map_y <= h - 1)
    return warped, valid


def masked_psnr(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (dB) over the pixels of ``mask`` (images in [0, 1]); NaN for an empty mask."""
    if not np.any(mask):
        return float("nan")
    return psnr(image[mask], reference[mask])


SSIM_RADIUS = 5  # half-width of the 11 x 11 SSIM window


def masked_ssim(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    """Mean of the SSIM map (evaluate.ssim's window and constants) over the pixels of ``mask`` whose
    whole window lies in ``mask`` (the mask eroded by the window's half-width), so pixels outside it
    (e.g. where a warp has no value) never enter; NaN if none is left."""
    inner = eroded(mask, SSIM_RADIUS)
    if not np.any(inner):
        return float("nan")
    _, full = structural_similarity(
        np.clip(image, 0, 1).astype(np.float64), np.asarray(reference, np.float64), gaussian_weights=True,
        sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=2, full=True)
    return float(full.mean(axis=2)[inner].mean())


def dark_hole_fraction(render: np.ndarray, reference: np.ndarray, ratio: float = 0.5, min_level: float = 0.1,
                       mask: np.ndarray | None = None) -> float:
    """Share of pixels (of ``mask``'s, if given) whose grey level in ``render`` is below ``ratio`` times
    the reference's where the reference is at least ``min_level`` (both smoothed by a 2-px Gaussian):
    holes and dark smears."""
    r = cv2.GaussianBlur(grey(render), (0, 0), 2.0)
    ref = cv2.GaussianBlur(grey(reference), (0, 0), 2.0)
    dark = (r < ratio * ref) & (ref >= min_level)
    return float(np.mean(dark if mask is None else dark[mask]))
