"""The observed pixels (host-side numpy): the pixel grid, checking and binning an
image, and choosing the pixels a fit compares."""

import math

import equinox as eqx
import numpy as np

# Pixels a strip of the image holds when it is binned strip by strip (the temporaries
# of one strip, not of the whole image).
_STRIP_PIXELS = 1 << 20


def pixel_centres(height: int, width: int, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """The pixel-centre coordinates of a `height` x `width` image, in pixels from the
    image centre: `x` (length `width`, right) and `y` (length `height`, up; row 0 at
    the top). Column $i$ is at $x = i + 1/2 - W/2$, row $j$ at $y = H/2 - j - 1/2$;
    broadcast them as `x[None, :]`, `y[:, None]` rather than building 2-D grids.

    **Returns:** `(x, y)`, 1-D arrays of `dtype` (exact: half-integers).
    """
    if min(height, width) < 1:
        raise ValueError(f"an image of {width} x {height} pixels has no pixel centres")
    x = (np.arange(width) + 0.5 - 0.5 * width).astype(dtype)
    y = (0.5 * height - (np.arange(height) + 0.5)).astype(dtype)
    return x, y


def pixel_edges(width: int, height: int, block: int, dtype):
    """Left/top edges (full-image pixels from the centre) of the `block` x `block`
    bins of a `width` x `height` image, centred crop when the size does not divide:
    `pixel_centres` moved half a pixel, every `block`-th (numpy: host-side constants,
    no dispatch for each bin size).

    **Returns:** `(x0, y0)`, read-only `(H // block, W // block)` broadcast views of
    1-D arrays of `dtype`.
    """
    wb, hb = width // block, height // block
    c0, r0 = (width - wb * block) // 2, (height - hb * block) // 2
    x, y = pixel_centres(height, width)
    x0 = (x[c0 : c0 + wb * block : block] - 0.5).astype(dtype)
    y0 = (y[r0 : r0 + hb * block : block] + 0.5).astype(dtype)
    return np.broadcast_to(x0[None, :], (hb, wb)), np.broadcast_to(y0[:, None], (hb, wb))


def real_image(image, name: str = "image") -> np.ndarray:
    """`image` as a float64 NumPy array, after checking that it holds real numbers:
    a complex, boolean, string or object array is a `TypeError` naming its dtype
    (NumPy would drop an imaginary part with only a warning)."""
    a = image if isinstance(image, np.ndarray) else np.asarray(image)
    if a.dtype.kind not in "iuf":
        raise TypeError(f"{name} of dtype {a.dtype} is not valid: expected real numbers "
                        "(an integer or floating-point array)")  # fmt: skip
    return np.asarray(a, np.float64)


def bin_means(img, block):
    """Means of the `block` x `block` bins of an image (centred crop)."""
    return bin_valid(img, None, block)[0]


def bin_valid(img, valid, block):
    """Means over the `valid` pixels (`None`: all) of the `block` x `block` bins of an
    image (centred crop when the size does not divide; 0 where a bin has none), and
    their counts. Strip by strip: the temporaries are a strip's, not the image's.

    **Returns:** `(means, counts)`, float64 and int `(H // block, W // block)`.
    """
    h, w = img.shape
    hb, wb = h // block, w // block
    r0, c0 = (h - hb * block) // 2, (w - wb * block) // 2
    s = np.empty((hb, wb))
    n = np.empty((hb, wb), np.int64)
    step = max(1, _STRIP_PIXELS // max(wb * block * block, 1))  # bin rows a strip
    cols = slice(c0, c0 + wb * block)
    for i in range(0, hb, step):
        j = min(i + step, hb)
        rows = slice(r0 + i * block, r0 + j * block)
        part = img[rows, cols]
        if valid is None:
            s[i:j] = part.reshape(j - i, block, wb, block).sum(axis=(1, 3))
            n[i:j] = block * block
        else:
            ok = valid[rows, cols]
            s[i:j] = np.where(ok, part, 0.0).reshape(j - i, block, wb, block).sum(axis=(1, 3))
            n[i:j] = ok.reshape(j - i, block, wb, block).sum(axis=(1, 3))
    return np.where(n > 0, s / np.maximum(n, 1), 0.0), n


class _PixelSets(eqx.Module):
    """The pixels a fit compares (host-side numpy): `fine` edges (x0, y0) of bins of
    side `block`, `coarse_edges` of blocks of side `coarse` (empty when `coarse` = 0),
    the means of their valid pixels `data` (fine, then coarse), the counts of those
    `count`, and where each lies: `rows`, `cols` (top-left, original pixels) and `side`."""

    fine: tuple
    coarse_edges: tuple
    data: np.ndarray
    count: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    side: np.ndarray
    block: int
    coarse: int
    shape: tuple  # of the original image

    @property
    def weight(self) -> np.ndarray:
        """sqrt(count): a weighted residual has the noise of one original pixel."""
        return np.sqrt(self.count)

    def bin_index(self) -> tuple[np.ndarray, np.ndarray]:
        """Row and column, in the image of `block` x `block` bins that `paint` makes, of
        each compared bin's top-left bin."""
        h, w = self.shape
        hb, wb = h // self.block, w // self.block
        r0, c0 = (h - hb * self.block) // 2, (w - wb * self.block) // 2
        return (self.rows - r0) // self.block, (self.cols - c0) // self.block

    def paint(self, values, fill=np.nan) -> np.ndarray:
        """`values` (one per compared bin) as an image of `block` x `block` bins, each
        coarse block filling its bins; `fill` where no bin lies or none is valid."""
        h, w = self.shape
        hb, wb = h // self.block, w // self.block
        out = np.full((hb, wb), fill, dtype=np.result_type(values, float))
        values = np.where(self.count > 0, values, fill)
        rows, cols = self.bin_index()
        for side in np.unique(self.side):
            sel = self.side == side
            q = int(side) // self.block
            rr, cc = rows[sel], cols[sel]
            for i in range(q):
                for j in range(q):
                    out[np.minimum(rr + i, hb - 1), np.minimum(cc + j, wb - 1)] = values[sel]
        return out


def grid_sets(img, valid, block) -> _PixelSets:
    """Every `block` x `block` bin (centred crop), as one set."""
    h, w = img.shape
    data, count = bin_valid(img, valid, block)
    x0, y0 = (np.asarray(v).ravel() for v in pixel_edges(w, h, block, np.float64))
    cols = np.round(x0 + 0.5 * w).astype(int)
    rows = np.round(0.5 * h - y0).astype(int)
    empty = (np.zeros(0), np.zeros(0))
    return _PixelSets((x0, y0), empty, data.ravel(), count.ravel().astype(float), rows, cols,
                      np.full(x0.size, block), block, 0, (h, w))  # fmt: skip


def pixel_sets(img, prof, rho_sh, max_pixels: int, block: int | None, *, valid=None,
               centre=(0.0, 0.0), structure=None) -> _PixelSets:  # fmt: skip
    """Full resolution (or bins of `block`, the finest the ring allows) on the shadow
    edge, the ring and wherever the image shows light; where the image is flat (inside
    the shadow, the far sky) blocks q times larger, q the factor that gives the fewest
    bins in all (at most `max_pixels`, where the bands allow).

    Fine bins: side `block` (default 1, or up to half the ring's radial width when the
    image is still too large, and up to that width when the bands alone hold more than
    `max_pixels`). The bands at full resolution, about `centre` (the hole's image,
    pixels from the image centre, y up): the ring radius +- 6 ring widths and the shadow
    edge (`prof.shadow_radius` where the profile shows it, and `rho_sh` unless NaN) +- 3
    pixels, each widened by a coarse block's diagonal; and every block whose mean stands
    above `structure` (data units; None: no such test). `valid` (bool, default all): the
    pixels compared.
    """
    h, w = img.shape
    valid = np.ones(img.shape, bool) if valid is None else np.asarray(valid, bool)
    given = block is not None
    if not given:
        block = 1
        while (h // block) * (w // block) > 4 * max_pixels and 2 * (block + 1) <= prof.ring_width:
            block += 1
    block = int(block)
    if (h // block) * (w // block) <= max_pixels:
        return grid_sets(img, valid, block)
    ring_lo = prof.ring_radius - 6.0 * prof.ring_width - 3.0
    ring_hi = prof.ring_radius + 6.0 * prof.ring_width + 3.0
    edges = [r for r in (rho_sh, prof.shadow_radius) if math.isfinite(r)]

    def choose(block):
        """The coarse factor q giving the fewest bins for fine bins of `block`:
        `(n, q, selected blocks, their edges, crop)`."""
        best = None
        for q in (2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 24, 32, 40, 48, 64, 96, 128):
            big = block * q
            hb, wb = h // big, w // big
            if hb < 2 or wb < 2 or (best is not None and big >= min(h, w) // 4):
                break
            bx, by = (np.asarray(v) for v in pixel_edges(w, h, big, np.float64))
            rc = np.hypot(bx + 0.5 * big - centre[0], by - 0.5 * big - centre[1])
            half = big / math.sqrt(2.0)
            lo_r, hi_r = rc - half, rc + half
            sel = (hi_r > ring_lo) & (lo_r < ring_hi)
            for e in edges:
                sel |= (hi_r > e - 3.0) & (lo_r < e + 3.0)
            r0, c0 = (h - hb * big) // 2, (w - wb * big) // 2
            crop = (slice(r0, r0 + hb * big), slice(c0, c0 + wb * big))
            if structure is not None:
                mean, _ = bin_valid(img[crop], valid[crop], big)
                sel |= mean > structure
            n = int(sel.sum()) * q * q + int((~sel).sum())
            if best is None or n < best[0]:
                best = (n, q, sel, bx, by, crop)
        return best

    # Where the band of structure alone holds more than `max_pixels` pixels, fine bins
    # of 2, 3, ... pixels, no wider than the ring's radial width (`k` follows the bin).
    n, q, sel, bx, by, crop = choose(block)
    while n > max_pixels and not given and block + 1 <= prof.ring_width:
        block += 1
        n, q, sel, bx, by, crop = choose(block)
    big = block * q
    # The fine bins of the selected blocks, and the coarse blocks elsewhere.
    sub = np.arange(q) * block
    fx = (bx[sel][:, None, None] + sub[None, None, :]).repeat(q, axis=1).ravel()
    fy = (by[sel][:, None, None] - sub[None, :, None]).repeat(q, axis=2).ravel()
    cols = np.round(fx + 0.5 * w).astype(int)
    rows = np.round(0.5 * h - fy).astype(int)
    win = (rows[:, None, None] + np.arange(block)[None, :, None],
           cols[:, None, None] + np.arange(block)[None, None, :])  # fmt: skip
    f_cnt = valid[win].sum(axis=(1, 2))
    f_sum = np.where(valid[win], img[win], 0.0).sum(axis=(1, 2))
    fine = np.where(f_cnt > 0, f_sum / np.maximum(f_cnt, 1), 0.0)
    coarse, c_cnt = bin_valid(img[crop], valid[crop], big)
    c_cols = np.round(bx[~sel] + 0.5 * w).astype(int)
    c_rows = np.round(0.5 * h - by[~sel]).astype(int)
    return _PixelSets(
        (fx, fy), (bx[~sel], by[~sel]), np.concatenate([fine, coarse[~sel]]),
        np.concatenate([f_cnt, c_cnt[~sel]]).astype(float), np.concatenate([rows, c_rows]),
        np.concatenate([cols, c_cols]),
        np.concatenate([np.full(fine.size, block), np.full(c_cols.size, big)]), block, big,
        (h, w),
    )  # fmt: skip


# Former names, kept while modules outside this one still import them by these.
