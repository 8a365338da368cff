"""An epoch's mini-batches (``batches.epoch_batches``) drawn on a torch device, for a fit that runs there.

On the host, an epoch's batching is some thirty numpy passes over the masked pixels, the event pairs and
their footprints' taps (sorts, a unique, counts): 45–70 ms an epoch at 256², most of a GPU's epoch of the
``paper`` preset, and the copy of its arrays to the device waits for the epoch before to end. Here the same
arrays are made where the fit reads them, from the same random tile offset and order (drawn on the host
from the same generator, and moved: a few thousand integers). Every step is an integer gather, scatter,
stable sort, sum or search, so the arrays are the host's, entry for entry (a test holds them to it). The
host reads back only what it must know, each batch's counts, in one read; the footprints' pixels outside
their batch (a unique of a selection) are the two other waits an epoch has for the device.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


@dataclass
class TilesThere:
    """What the drawing needs of a problem, on its device (int64 each): every masked pixel's ``row`` and
    ``col`` (P,), its first importance sample ``sample_start`` and their count ``sample_count`` (P,) (the
    samples are stored by pixel), each sample's frame ``sample_frame``; the usable pairs ``events`` (E,)
    (indices into all pairs), each one's ``event_anchor`` pixel (E,) and ``event_taps`` (E, fan); the TV
    pairs ``tv_pairs`` (Q, 2)."""

    row: Tensor
    col: Tensor
    sample_start: Tensor
    sample_count: Tensor
    sample_frame: Tensor
    events: Tensor
    event_anchor: Tensor
    event_taps: Tensor
    tv_pairs: Tensor


@dataclass
class DrawnThere:
    """An epoch's batches: ``fields`` by the name of ``batches.Batch``'s field, the batches' rows one after
    the other, on the device, and for each batch (B,) on the host, ``own`` frame pixels, pixels ``outside``
    its tiles that its pairs' footprints reach, importance ``samples``, event ``pairs`` and ``tv`` pairs."""

    fields: dict[str, Tensor]
    own: np.ndarray
    outside: np.ndarray
    samples: np.ndarray
    pairs: np.ndarray
    tv: np.ndarray


def moved(arrays: dict[str, np.ndarray], device: torch.device) -> dict[str, Tensor]:
    """These int64 arrays on ``device``, moved in one copy: on a GPU a copy for each batch and array would
    wait for the device each time."""
    there = torch.as_tensor(np.concatenate([a.ravel() for a in arrays.values()], dtype=np.int64), device=device)
    out, start = {}, 0
    for name, a in arrays.items():
        out[name] = there[start:start + a.size].view(a.shape)
        start += a.size
    return out


def _counts(ascending: Tensor, n: int) -> Tensor:
    """(n,) int64: the entries of ``ascending`` (sorted) equal to each of 0 … n − 1: by searches, where a
    count by ``index_add_`` would send thousands of atomic adds to each of a few batches (and
    ``torch.bincount`` reads its maximum first)."""
    bounds = torch.searchsorted(ascending, torch.arange(n + 1, dtype=ascending.dtype, device=ascending.device))
    return bounds[1:] - bounds[:-1]


def _starts(count: Tensor) -> Tensor:
    """Where each of consecutive blocks of ``count`` entries starts."""
    return torch.cumsum(count, 0) - count


def draw_there(tiles: TilesThere, shift: Tensor, rank: Tensor, tiles_across: int, batch_pixels: int, tile: int,
               frames: int) -> DrawnThere:
    """``batches.epoch_batches`` on the tiles' device, for the tile offset ``shift`` (2,) and the tiles'
    random order ``rank`` (tiles,) the host drew (``batches._draw_order``; ``tiles_across`` tiles a row of
    them), ``frames`` frames; the fields' order and meaning are ``batches.epoch_batches``'s."""
    p = tiles.row.numel()
    device = tiles.row.device
    arange = torch.arange(p, device=device)
    tile_rank = rank[((tiles.row + shift[0]) // tile) * tiles_across + (tiles.col + shift[1]) // tile]
    # tiles in random order; a batch closes once it holds batch_pixels pixels
    size = _counts(torch.sort(tile_rank).values, rank.numel())
    batch_of_rank = _starts(size) // batch_pixels
    # a tile larger than batch_pixels skips batch numbers: number the batches densely, in the pixels'
    # order by batch (the same order for either numbering)
    numbers = batch_of_rank[tile_rank]
    by_pixel = torch.argsort(numbers, stable=True)
    numbers = numbers[by_pixel]
    zero = torch.zeros(1, dtype=torch.int64, device=device)
    sorted_batch = torch.cumsum(torch.cat([zero, (numbers[1:] != numbers[:-1]).to(torch.int64)]), 0)
    pixel_batch = torch.empty_like(sorted_batch)
    pixel_batch[by_pixel] = sorted_batch
    event_batch = pixel_batch[tiles.event_anchor]
    first, second = pixel_batch[tiles.tv_pairs[:, 0]], pixel_batch[tiles.tv_pairs[:, 1]]
    pair_batch = torch.where(first == second, first, -1)
    by_event, by_pair = (torch.argsort(b, stable=True) for b in (event_batch, pair_batch))
    # the batches' numbers are below this, whatever the draw
    bound = p // batch_pixels + 1
    own_count = _counts(sorted_batch, bound)
    own_start = _starts(own_count)
    event_count = _counts(event_batch[by_event], bound)
    pair_count = _counts(pair_batch[by_pair], bound)
    samples_sum = torch.cat([zero, torch.cumsum(tiles.sample_count[by_pixel], 0)])
    sample_count = samples_sum[own_start + own_count] - samples_sum[own_start]
    # each pixel's place among its batch's own pixels
    own_rank = torch.empty_like(arange)
    own_rank[by_pixel] = arange - own_start[sorted_batch]
    # the footprints' pixels outside their pair's batch, unique and ascending within each batch
    taps = tiles.event_taps[by_event]
    tap_batch = event_batch[by_event][:, None].expand_as(taps)
    key = tap_batch * p + taps
    outside = pixel_batch[taps] != tap_batch
    extra_key = torch.unique(key[outside])
    extra_batch, extra_pixel = extra_key // p, extra_key % p
    extra_count = _counts(extra_batch, bound)
    # what the host must know, in one read: the batches' number and their counts
    counts = torch.stack([(own_count > 0).to(torch.int64), own_count, extra_count, sample_count, event_count, pair_count]).cpu().numpy()
    n_batches = int(counts[0].sum())
    own, outside_count, samples, pairs, tv = counts[1:, :n_batches]
    extra_place = own_count[extra_batch] + torch.arange(extra_key.numel(), device=device) - _starts(extra_count)[extra_batch]
    local_taps = own_rank[taps]
    if extra_key.numel():
        found = torch.searchsorted(extra_key, key).clamp_(max=extra_key.numel() - 1)
        local_taps = torch.where(outside, extra_place[found], local_taps)
    pixel_start = _starts(own_count + extra_count)
    pixels = torch.empty(p + extra_key.numel(), dtype=torch.int64, device=device)
    pixels[pixel_start[sorted_batch] + own_rank[by_pixel]] = by_pixel
    pixels[pixel_start[extra_batch] + extra_place] = extra_pixel
    # frame rows frame-major within each batch: frame·P + pixel for each frame, then the next
    own_of = own_count[sorted_batch]
    row_start = frames * own_start[sorted_batch] + own_rank[by_pixel]
    frame_rows = torch.empty(frames * p, dtype=torch.int64, device=device)
    for k in range(frames):
        frame_rows[row_start + k * own_of] = k * p + by_pixel
    pairs_in = tiles.tv_pairs[by_pair[by_pair.numel() - int(tv.sum()):]]
    fields = {"pixels": pixels, "frame_rows": frame_rows, "events": tiles.events[by_event], "event_taps": local_taps,
              "tv_pairs": own_rank[pairs_in],
              **samples_there(tiles.sample_start, tiles.sample_count, tiles.sample_frame, by_pixel, own_rank[by_pixel], own_of)}
    return DrawnThere(fields=fields, own=own, outside=outside_count, samples=samples, pairs=pairs, tv=tv)


def samples_there(start: Tensor, count: Tensor, frame: Tensor, order: Tensor, rank: Tensor, own: Tensor) -> dict[str, Tensor]:
    """``batches._samples`` on the device: the importance samples of the masked pixels ``order`` (P,)
    (``start`` and ``count`` (P,) each pixel's first sample and their number, ``frame`` each sample's
    frame), each pixel's in their stored order: "samples" their indices into all samples,
    "sample_pixel" the ``rank`` (P,) of their pixel among its batch's own pixels, "sample_group"
    frame·``own`` + rank (``own`` (P,) each pixel's batch's count of own pixels)."""
    total = int(frame.numel())
    count = count[order]
    offset = torch.repeat_interleave(start[order] - (torch.cumsum(count, 0) - count), count, output_size=total)
    samples = torch.arange(total, device=count.device) + offset
    sample_pixel = torch.repeat_interleave(rank, count, output_size=total)
    group = frame[samples] * torch.repeat_interleave(own, count, output_size=total) + sample_pixel
    return {"samples": samples, "sample_pixel": sample_pixel, "sample_group": group}
