"""What one Adam step of DualResPS fits (``Batch``): all of the problem (``full_batch``), or one of an
epoch's mini-batches of spatial tiles (``epoch_batches``), as the paper's network trains.

An epoch of mini-batches is a pass over all masked pixels in batches of about ``batch_pixels`` frame
pixels: square tiles of ``tile`` frame pixels, shuffled and offset at random every epoch, each batch
taking its pixels' frames and importance samples, the event pairs of the super pixels anchored in its
tiles, and the TV pairs inside it (as LL22a trains). ``EpochBatches`` holds them as arrays over the
whole epoch, drawn with numpy on the host, or on the problem's device where that is not the CPU
(``batches_device``, the same arrays): split into batches of their own sizes (``batches``), or packed
into rows of one size (``packed``, each field padded to a ``Capacity``), which a step replayed as a CUDA
graph reads (``graphed``) through an ``Unpacker``.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from pstoolkit._shared import devices
from pstoolkit_dualres.batches_device import TilesThere, draw_there, moved
from pstoolkit_dualres.problem import Problem

# The per-batch counts a packed row starts with: own pixels, pixels outside, samples, pairs, TV pairs.
COUNTS = 5


@dataclass
class Valid:
    """Which rows of a padded field hold data: ``mask`` (N,) 1.0 or 0.0 in the problem's dtype, and
    ``count`` their number, a 0-dim tensor."""

    mask: Tensor
    count: Tensor


@dataclass
class Padding:
    """The rows of a packed batch that hold data: of its pixels (own and outside), of its frame rows,
    importance samples, event pairs and TV pairs."""

    pixel: Valid
    frame: Valid
    sample: Valid
    event: Valid
    tv: Valid


@dataclass
class Batch:
    """One Adam step's share of the problem. ``pixels`` (N,) the masked-pixel positions the field
    is evaluated at (None: all, in order), the first ``frame_pixels`` of them (None: all) the pixels
    whose frames are fitted; ``frame_rows`` their rows of ``FrameTerms.measured`` in frame-major order
    (None: all); ``samples`` their importance samples (None: all) with ``sample_pixel`` and
    ``sample_group`` (frame·frame_pixels + pixel) in local positions; ``events`` the event pairs
    (indices into all pairs) with ``event_taps`` in local positions; ``tv_pairs`` local neighbour
    pairs; ``padding`` the rows that hold data when the fields are padded (None: all do);
    ``frame_chunk`` pixels per chunk of the shared grid's frame term (None: as ``losses.frame_chunk``
    finds the device's memory)."""

    pixels: Tensor | None
    frame_pixels: int | None
    frame_rows: Tensor | None
    samples: Tensor | None
    sample_pixel: Tensor
    sample_group: Tensor
    events: Tensor
    event_taps: Tensor
    tv_pairs: Tensor
    padding: Padding | None = None
    frame_chunk: int | None = None


def full_batch(problem: Problem, events: Tensor, frame_chunk: int | None = None) -> Batch:
    """Every pixel and sample, the event pairs ``events``, the frame term in chunks of ``frame_chunk``
    pixels (None: as the device's memory allows)."""
    return Batch(pixels=None, frame_pixels=None, frame_rows=None, samples=None,
                 sample_pixel=problem.frames.sample_pixel, sample_group=problem.frames.sample_group,
                 events=events, event_taps=problem.events.taps[events], tv_pairs=problem.geometry.tv_pairs,
                 frame_chunk=frame_chunk)


@dataclass(frozen=True)
class Capacity:
    """Rows of each field of a packed batch: ``own`` frame pixels, ``outside`` pixels the pairs'
    footprints reach beyond its tiles, importance ``samples``, event ``pairs`` and ``tv`` pairs, for
    ``frames`` frames and ``fan`` taps a pair."""

    own: int
    outside: int
    samples: int
    pairs: int
    tv: int
    frames: int
    fan: int

    @property
    def width(self) -> int:
        """Entries of a packed row: the counts, pixels, frame rows, three per sample, pairs and their
        taps, and two per TV pair."""
        return (COUNTS + self.own + self.outside + self.frames * self.own + 3 * self.samples
                + self.pairs * (1 + self.fan) + 2 * self.tv)

    def union(self, other: Capacity) -> Capacity:
        """Each field's larger capacity of the two."""
        return dataclasses.replace(self, **{name: max(getattr(self, name), getattr(other, name))
                                            for name in ("own", "outside", "samples", "pairs", "tv")})

    def covers(self, other: Capacity) -> bool:
        """Whether every field of ``other`` fits in this one's."""
        return all(getattr(self, name) >= getattr(other, name) for name in ("own", "outside", "samples", "pairs", "tv"))

    def grown(self, share: float) -> Capacity:
        """Each field at least ``share`` times larger, rounded up to the next 2^k or 3·2^k (an empty one
        stays empty): epochs and stages whose batches differ a little share their capacities, and so a
        compiled step (whose shapes are fixed) and its graph."""
        def up(n: int) -> int:
            # an empty field stays empty: a padded row must point at some row of the problem
            if n == 0:
                return 0
            need = int(np.ceil(n * share))
            power = 1 << max(need - 1, 0).bit_length()
            return 3 * power // 4 if power >= 4 and 3 * power // 4 >= need else power

        return Capacity(own=up(self.own), outside=up(self.outside), samples=up(self.samples), pairs=up(self.pairs),
                        tv=up(self.tv), frames=self.frames, fan=self.fan)


@dataclass
class Tiling:
    """What ``epoch_batches`` needs of a problem: as numpy, each masked pixel's (row, column), each
    usable event pair (``events``, indices into all pairs) with its anchor pixel (its footprint's
    largest tap) and taps, and the TV pairs; on the problem's device, each pixel's first importance
    sample and count of them (the samples are stored by pixel) and each sample's frame."""

    row: np.ndarray
    col: np.ndarray
    events: np.ndarray
    event_anchor: np.ndarray
    event_taps: np.ndarray
    tv_pairs: np.ndarray
    sample_start: Tensor
    sample_count: Tensor
    sample_frame: Tensor
    _there: TilesThere | None = dataclasses.field(default=None, repr=False)

    def there(self) -> TilesThere:
        """The tiling on the samples' device (``batches_device``), moved there once."""
        if self._there is None:
            arrays = moved({"row": self.row, "col": self.col, "events": self.events, "event_anchor": self.event_anchor,
                            "event_taps": self.event_taps, "tv_pairs": self.tv_pairs}, self.sample_count.device)
            self._there = TilesThere(sample_start=self.sample_start, sample_count=self.sample_count,
                                     sample_frame=self.sample_frame, **arrays)
        return self._there

    @classmethod
    def of(cls, problem: Problem) -> Tiling:
        geometry, frames = problem.geometry, problem.frames
        p = geometry.pixels.size
        row, col = np.divmod(geometry.pixels, geometry.width)
        events = problem.events.usable.cpu().numpy()
        taps = problem.events.taps.cpu().numpy()[events]
        weight = problem.events.tap_weight_now.cpu().numpy()[events]
        anchor = taps[np.arange(len(taps)), np.argmax(weight, axis=1)] if taps.size else np.zeros(0, np.int64)
        count = torch.bincount(frames.sample_pixel, minlength=p)
        return cls(row=row, col=col, events=events, event_anchor=anchor, event_taps=taps,
                   tv_pairs=geometry.tv_pairs.cpu().numpy(), sample_start=torch.cumsum(count, 0) - count,
                   sample_count=count, sample_frame=frames.sample_group // max(p, 1))


def _starts(count: np.ndarray) -> np.ndarray:
    """Where each of consecutive blocks of ``count`` entries starts."""
    return np.cumsum(count) - count


def _draw_order(problem: Problem, tile: int, generator: torch.Generator) -> tuple[np.ndarray, int, np.ndarray]:
    """An epoch's random offset (2,) of the tiles of ``tile`` frame pixels a side, their number in a row
    (columns), and their random order (each tile's rank), drawn from ``generator``."""
    shift = torch.randint(0, tile, (2,), generator=generator).numpy()
    rows = (problem.geometry.height + tile) // tile + 1
    cols = (problem.geometry.width + tile) // tile + 1
    return shift, cols, torch.randperm(rows * cols, generator=generator).numpy()


def _capacity(own: np.ndarray, outside: np.ndarray, samples: np.ndarray, pairs: np.ndarray, tv: np.ndarray, frames: int,
              fan: int) -> Capacity:
    """The rows of the largest batch in each field, from each batch's counts (B,)."""
    return Capacity(own=int(own.max()), outside=int(outside.max()), samples=int(samples.max()), pairs=int(pairs.max()),
                    tv=int(tv.max()), frames=frames, fan=fan)


@dataclass
class _Grouping:
    """The host's part of an epoch's batching (``epoch_batches`` on the CPU): the batch of each masked pixel,
    pair and TV pair, their orders by batch, each batch's counts, each pixel's place among its
    batch's own, and the pixels the pairs' footprints reach outside their batch (``extra_*``)."""

    pixel_batch: np.ndarray
    by_pixel: np.ndarray
    by_event: np.ndarray
    by_pair: np.ndarray
    own_count: np.ndarray
    event_count: np.ndarray
    pair_count: np.ndarray
    sample_count: np.ndarray
    own_rank: np.ndarray
    taps: np.ndarray
    tap_batch: np.ndarray
    outside: np.ndarray
    extra_key: np.ndarray
    extra_count: np.ndarray

    @classmethod
    def draw(cls, problem: Problem, tiling: Tiling, batch_pixels: int, tile: int, generator: torch.Generator) -> _Grouping:
        """A random offset of the tiles of ``tile`` frame pixels a side, the tiles in random order
        grouped into batches of about ``batch_pixels`` pixels, drawn from ``generator``; at least one
        masked pixel."""
        p = problem.geometry.pixels.size
        shift, cols, rank = _draw_order(problem, tile, generator)
        tile_of = ((tiling.row + shift[0]) // tile) * cols + (tiling.col + shift[1]) // tile
        # tiles in random order; a batch closes once it holds batch_pixels pixels
        size = np.bincount(rank[tile_of], minlength=rank.size)
        batch_of_rank = _starts(size) // batch_pixels
        # a tile larger than batch_pixels skips batch numbers: number the batches densely
        pixel_batch = np.unique(batch_of_rank[rank[tile_of]], return_inverse=True)[1].reshape(-1)
        event_batch = pixel_batch[tiling.event_anchor]
        pair_batch = np.where(pixel_batch[tiling.tv_pairs[:, 0]] == pixel_batch[tiling.tv_pairs[:, 1]],
                              pixel_batch[tiling.tv_pairs[:, 0]], -1)
        by_pixel, by_event, by_pair = (np.argsort(b, kind="stable") for b in (pixel_batch, event_batch, pair_batch))
        n_batches = int(pixel_batch.max()) + 1
        own_count = np.bincount(pixel_batch, minlength=n_batches)
        # each pixel's place among its batch's own pixels
        own_rank = np.empty(p, dtype=np.int64)
        own_rank[by_pixel] = np.arange(p) - np.repeat(_starts(own_count), own_count)
        # the footprints' pixels outside their pair's batch, unique and ascending within each batch
        taps = tiling.event_taps[by_event]
        tap_batch = np.repeat(event_batch[by_event], taps.shape[1]).reshape(taps.shape)
        outside = pixel_batch[taps] != tap_batch
        extra_key = np.unique(tap_batch[outside] * p + taps[outside])
        sample_count = np.bincount(pixel_batch, weights=tiling.sample_count.cpu().numpy(), minlength=n_batches)
        return cls(pixel_batch=pixel_batch, by_pixel=by_pixel, by_event=by_event, by_pair=by_pair, own_count=own_count,
                   event_count=np.bincount(event_batch, minlength=n_batches),
                   pair_count=np.bincount(pair_batch[pair_batch >= 0], minlength=n_batches),
                   sample_count=sample_count.astype(np.int64), own_rank=own_rank, taps=taps, tap_batch=tap_batch,
                   outside=outside, extra_key=extra_key, extra_count=np.bincount(extra_key // p, minlength=n_batches))

    def capacity(self, frames: int) -> Capacity:
        """The rows of the largest batch in each field."""
        return _capacity(self.own_count, self.extra_count, self.sample_count, self.event_count, self.pair_count, frames,
                         int(self.taps.shape[1]))


def epoch_batches(problem: Problem, tiling: Tiling, batch_pixels: int, tile: int, generator: torch.Generator) -> EpochBatches:
    """One epoch's mini-batches (see the module docstring): a random offset of the tiles of ``tile``
    frame pixels a side, the tiles in random order grouped into batches of about ``batch_pixels``
    pixels, drawn from ``generator``.

    A batch's pixels are its own (in the masked pixels' order), then the pixels its event pairs'
    footprints reach outside its tiles (ascending); its frame rows and samples follow its own pixels'
    order. Every batch is built at once, as arrays over the epoch: with numpy on the host, or where the
    problem's device is not the CPU, there (``batches_device``: the same arrays, from the same draws)."""
    p = problem.geometry.pixels.size
    frames = problem.frames.count
    if p == 0:
        return EpochBatches(np.zeros(0, np.int64), {}, {}, Capacity(0, 0, 0, 0, 0, frames, 0))
    if not devices.on_host(problem.device):
        shift, cols, rank = _draw_order(problem, tile, generator)
        order = moved({"shift": shift, "rank": rank}, problem.device)
        drawn = draw_there(tiling.there(), order["shift"], order["rank"], cols, batch_pixels, tile, frames)
        return _assembled(drawn.fields, drawn.own, drawn.outside, drawn.samples, drawn.pairs, drawn.tv, frames,
                          int(tiling.event_taps.shape[1]))
    g = _Grouping.draw(problem, tiling, batch_pixels, tile, generator)
    own_count, own_rank, by_pixel, pixel_batch = g.own_count, g.own_rank, g.by_pixel, g.pixel_batch
    own_of = own_count[pixel_batch[by_pixel]]
    extra_batch, extra_pixel = np.divmod(g.extra_key, p)
    extra_place = own_count[extra_batch] + np.arange(g.extra_key.size) - np.repeat(_starts(g.extra_count), g.extra_count)
    local_taps = own_rank[g.taps]
    local_taps[g.outside] = extra_place[np.searchsorted(g.extra_key, g.tap_batch[g.outside] * p + g.taps[g.outside])]
    pixel_count = own_count + g.extra_count
    pixels = np.empty(int(pixel_count.sum()), dtype=np.int64)
    pixel_start = _starts(pixel_count)
    pixels[pixel_start[pixel_batch[by_pixel]] + own_rank[by_pixel]] = by_pixel
    pixels[pixel_start[extra_batch] + extra_place] = extra_pixel
    # frame rows frame-major within each batch: frame·P + pixel for each frame, then the next
    frame_rows = np.empty(frames * p, dtype=np.int64)
    row_start = frames * _starts(own_count)[pixel_batch[by_pixel]] + own_rank[by_pixel]
    for k in range(frames):
        frame_rows[row_start + k * own_of] = k * p + by_pixel
    pairs = tiling.tv_pairs[g.by_pair[g.by_pair.size - int(g.pair_count.sum()):]]
    fields = {name: torch.from_numpy(values) for name, values in (
        ("pixels", pixels), ("frame_rows", frame_rows), ("events", tiling.events[g.by_event]), ("event_taps", local_taps),
        ("tv_pairs", own_rank[pairs]))}
    fields.update(_samples(tiling, by_pixel, own_rank[by_pixel], own_of))
    return _assembled(fields, own_count, g.extra_count, g.sample_count, g.event_count, g.pair_count, frames, int(g.taps.shape[1]))


def _assembled(fields: dict[str, Tensor], own: np.ndarray, outside: np.ndarray, samples: np.ndarray, pairs: np.ndarray,
               tv: np.ndarray, frames: int, fan: int) -> EpochBatches:
    """The ``EpochBatches`` of an epoch's ``fields`` and each batch's counts (B,) of own pixels, pixels
    outside, samples, event pairs and TV pairs."""
    rows = {"pixels": own + outside, "frame_rows": frames * own, "samples": samples, "sample_pixel": samples,
            "sample_group": samples, "events": pairs, "event_taps": pairs, "tv_pairs": tv}
    return EpochBatches(own, {name: fields[name] for name in rows}, rows, _capacity(own, outside, samples, pairs, tv, frames, fan))


def drawn_capacity(problem: Problem, tiling: Tiling, batch_pixels: int, tile: int, generator: torch.Generator, epochs: int) -> Capacity:
    """The rows of the largest batch in each field over ``epochs`` epochs drawn from ``generator`` (on
    the host, the batches' counts only; on a device, the epochs drawn there)."""
    frames = problem.frames.count
    if problem.geometry.pixels.size == 0:
        return Capacity(0, 0, 0, 0, 0, frames, 0)
    if not devices.on_host(problem.device):
        needs = [epoch_batches(problem, tiling, batch_pixels, tile, generator).needs for _ in range(epochs)]
    else:
        needs = [_Grouping.draw(problem, tiling, batch_pixels, tile, generator).capacity(frames) for _ in range(epochs)]
    return functools.reduce(Capacity.union, needs)


@dataclass
class EpochBatches:
    """An epoch's mini-batches as arrays over the epoch: ``own`` (B,) each batch's own frame pixels;
    ``fields`` by the name of ``Batch``'s field, the batches' rows one after the other, on the
    problem's device; ``rows`` by name (B,) each batch's count of them; ``needs`` the rows of the
    largest batch in each field."""

    own: np.ndarray
    fields: dict[str, Tensor]
    rows: dict[str, np.ndarray]
    needs: Capacity

    def __len__(self) -> int:
        return int(self.own.size)

    def batches(self) -> list[Batch]:
        """Each batch with fields of its own sizes (views into the epoch's arrays)."""
        parts = {name: torch.split(value, self.rows[name].tolist()) for name, value in self.fields.items()}
        return [Batch(frame_pixels=int(n), **{name: split[b] for name, split in parts.items()}) for b, n in enumerate(self.own)]

    def packed(self, capacity: Capacity) -> Tensor:
        """(B, ``capacity.width``) int64 on the fields' device, a row a batch: its counts (own pixels,
        pixels outside, samples, pairs, TV pairs), then each field padded to its capacity: own pixels
        at [0, own), those outside from ``capacity.own`` on (the pairs' taps renumbered so), frame rows
        frame·``capacity.own`` + pixel, sample groups likewise; padding points at row 0 of whatever
        it indexes (``Unpacker``'s masks leave it out). Every field must fit (``capacity.covers``)."""
        b, c = len(self), capacity
        device = self.fields["pixels"].device
        # the batches' counts (those of the row's head, then the pixels' and frame rows') in one copy from
        # the host: on a GPU each copy from pageable memory waits for the work queued before it
        heads = (self.own, self.rows["pixels"] - self.own, self.rows["samples"], self.rows["events"], self.rows["tv_pairs"])
        counts = torch.as_tensor(np.stack([*heads, self.rows["pixels"], self.rows["frame_rows"]], axis=1), device=device)
        out = torch.zeros((b, c.width), dtype=torch.int64, device=device)
        out[:, :COUNTS] = counts[:, :COUNTS]
        own = counts[:, 0]
        samples, events, tv, pixels, frame_rows = (_rows_of(counts[:, column], int(self.rows[name].sum())) for column, name in
                                                   enumerate(("samples", "events", "tv_pairs", "pixels", "frame_rows"), start=2))
        place, n = pixels.place, own[pixels.batch]
        offset = _pad_into(out, COUNTS, c.own + c.outside, self.fields["pixels"], pixels,
                           torch.where(place < n, place, place - n + c.own))
        # frame rows come frame-major: frame k of a batch of n own pixels at k·n + i, padded to k·own + i
        place, n = frame_rows.place, own[frame_rows.batch]
        offset = _pad_into(out, offset, c.frames * c.own, self.fields["frame_rows"], frame_rows, place // n * c.own + place % n)
        sample_pixel = self.fields["sample_pixel"]
        group = (self.fields["sample_group"] - sample_pixel) // own[samples.batch] * c.own + sample_pixel
        for values in (self.fields["samples"], sample_pixel, group):
            offset = _pad_into(out, offset, c.samples, values, samples)
        offset = _pad_into(out, offset, c.pairs, self.fields["events"], events)
        taps, n = self.fields["event_taps"], own[events.batch][:, None]
        offset = _pad_into(out, offset, c.pairs, torch.where(taps < n, taps, taps - n + c.own), events)
        _pad_into(out, offset, c.tv, self.fields["tv_pairs"], tv)
        return out


@dataclass(frozen=True)
class _Rows:
    """A field's rows, the batches' one after the other, on the device: each row's ``batch`` (N,) and
    its ``place`` (N,) within it."""

    batch: Tensor
    place: Tensor


def _rows_of(count: Tensor, total: int) -> _Rows:
    """The ``_Rows`` of ``count`` (B,) rows a batch, ``total`` (their sum, known on the host: the device
    is not read)."""
    batch = torch.repeat_interleave(torch.arange(count.shape[0], device=count.device), count, output_size=total)
    start = torch.cumsum(count, 0) - count
    return _Rows(batch, torch.arange(total, device=count.device) - start[batch])


def _pad_into(out: Tensor, offset: int, capacity: int, values: Tensor, rows: _Rows, place: Tensor | None = None) -> int:
    """Write a field (``values`` (N, ...) in its ``rows``) into columns [offset, offset + ``capacity``·row
    size) of ``out`` (B, W), each row at its ``place`` (default: its place within its batch); the offset
    after it."""
    size = int(np.prod(values.shape[1:], dtype=np.int64))
    if values.shape[0]:
        block = out[:, offset:offset + capacity * size].view(out.shape[0], capacity, size)
        block[rows.batch, rows.place if place is None else place] = values.reshape(-1, size)
    return offset + capacity * size


class Unpacker:
    """The padded ``Batch`` of a packed row of ``capacity`` (``EpochBatches.packed``), its ``padding``
    masks in ``dtype``: views into the row, and masks from its counts in a few kernels (a row's
    positions against the count that bounds each), with no read of the device, so that a CUDA graph
    may capture it."""

    def __init__(self, capacity: Capacity, dtype: torch.dtype, device: torch.device) -> None:
        c = self.capacity = capacity
        self.dtype = dtype
        # the masks' rows: own pixels, pixels outside, frame rows (own pixels for each frame), samples,
        # pairs, TV pairs; each row's place and which count bounds it
        spans = [(c.own, 0), (c.outside, 1), *[(c.own, 0)] * c.frames, (c.samples, 2), (c.pairs, 3), (c.tv, 4)]
        self.place = torch.cat([torch.arange(n, device=device) for n, _ in spans])
        self.bound = torch.cat([torch.full((n,), which, device=device) for n, which in spans])
        self.rows = [c.own + c.outside, c.frames * c.own, c.samples, c.pairs, c.tv]
        self.fields = (("pixels", c.own + c.outside, 1), ("frame_rows", c.frames * c.own, 1), ("samples", c.samples, 1),
                       ("sample_pixel", c.samples, 1), ("sample_group", c.samples, 1), ("events", c.pairs, 1),
                       ("event_taps", c.pairs, c.fan), ("tv_pairs", c.tv, 2))

    def __call__(self, row: Tensor) -> Batch:
        c = self.capacity
        counts = row[:COUNTS]
        offset = COUNTS
        fields: dict[str, Tensor] = {}
        for name, rows, size in self.fields:
            part = row[offset:offset + rows * size]
            fields[name] = part.view(rows, size) if size > 1 else part
            offset += rows * size
        pixel, frame, sample, event, tv = torch.split((self.place < counts[self.bound]).to(self.dtype), self.rows)
        count = counts.to(self.dtype)
        padding = Padding(pixel=Valid(pixel, count[0] + count[1]), frame=Valid(frame, count[0] * c.frames),
                          sample=Valid(sample, count[2]), event=Valid(event, count[3]), tv=Valid(tv, count[4]))
        return Batch(frame_pixels=c.own, padding=padding, **fields)


def _samples(tiling: Tiling, order: np.ndarray, rank: np.ndarray, own: np.ndarray) -> dict[str, Tensor]:
    """The importance samples of the masked pixels ``order`` (P,), each pixel's in their stored order:
    "samples" their indices into all samples, "sample_pixel" the ``rank`` of their pixel among its
    batch's own pixels, "sample_group" frame·``own`` + rank (``own`` each pixel's batch's count of own
    pixels); ``batches_device.samples_there`` on a device."""
    start, count, frame = tiling.sample_start.numpy(), tiling.sample_count.numpy(), tiling.sample_frame.numpy()
    count = count[order]
    offset = np.repeat(start[order] - (np.cumsum(count) - count), count)
    samples = np.arange(frame.size, dtype=np.int64) + offset
    sample_pixel = np.repeat(rank, count)
    group = frame[samples] * np.repeat(own, count) + sample_pixel
    return {"samples": torch.from_numpy(samples), "sample_pixel": torch.from_numpy(sample_pixel), "sample_group": torch.from_numpy(group)}
