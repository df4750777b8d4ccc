"""The surfel store: struct-of-arrays torch tensors with geometric growth and spatial chunks.

Slots ``[0, n)`` are in creation order (appends go to the end; compaction keeps the order), so
surfels created by one frame are contiguous and each fixed-size *chunk* of slots covers a compact
piece of surface.  Every chunk keeps a conservative axis-aligned bounding box (positions +- radius)
and view culling tests the boxes against the frustum first, so the per-surfel work of a frame
follows the number of surfels near the view, not the size of the map.  Removed surfels are only
marked dead; the store squeezes them out (order-preserving) once enough have accumulated.
"""
from __future__ import annotations

import math

import torch

_INF = float("inf")

# surfel slots allocated up front (the store grows geometrically beyond them)
INITIAL_CAPACITY = 1 << 16
# capacity growth factor when the store is full (geometric growth: amortised O(1) appends)
GROWTH_FACTOR = 2.0
# surfels per spatial chunk; each chunk keeps a bounding box so that view culling touches only the
# chunks inside the frustum (cost follows the visible surfels); at least 64
CHUNK_SIZE = 256
# the store is compacted (removed slots squeezed out, order kept) once this fraction of its slots
# are dead, in (0, 1]
COMPACT_FRACTION = 0.25
# cell size (mm) of the Z-order curve along which surfels past their unstable window are
# re-ordered in blocks (compact chunks, tight culling); 0 disables the re-ordering
SORT_CELL_MM = 1.0


def take(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``x[idx]`` along dim 0 for an int64 index (``index_select``: much faster than ``x[idx]`` on CPU)."""
    return x.index_select(0, idx)


def to_columns(x: torch.Tensor) -> torch.Tensor:
    """``(N, C)`` -> contiguous ``(C, N)``, equal to ``x.T.contiguous()`` (which torch copies element
    by element on a CPU: stacking the few columns is about 5x faster)."""
    return torch.stack(x.unbind(1))


def to_rows(x: torch.Tensor) -> torch.Tensor:
    """``(C, N)`` -> contiguous ``(N, C)``, equal to ``x.T.contiguous()`` (see :func:`to_columns`)."""
    return torch.stack(x.unbind(0), 1)


def _morton3(x: torch.Tensor) -> torch.Tensor:
    """Spread the low 21 bits of int64 ``x`` to every third bit (3-D Morton / Z-order code)."""
    x = x & 0x1FFFFF
    x = (x | (x << 32)) & 0x1F00000000FFFF
    x = (x | (x << 16)) & 0x1F0000FF0000FF
    x = (x | (x << 8)) & 0x100F00F00F00F00F
    x = (x | (x << 4)) & 0x10C30C30C30C30C3
    x = (x | (x << 2)) & 0x1249249249249249
    return x


class SurfelStore:
    """Surfel attributes, one tensor per attribute, slots ``[0, n)`` in use (some may be dead).

    Attributes (all length ``capacity``; only ``[:n]`` is meaningful):
        pos: ``(C, 3)`` float32 world position, mm.
        normal: ``(C, 3)`` float32 unit world normal (pointing towards the cameras that saw it).
        radius: ``(C,)`` float32 disc radius, mm.
        color: ``(C, 3)`` float32 RGB in [0, 1].
        conf: ``(C,)`` float32 accumulated confidence.
        t_init: ``(C,)`` int32 frame index of creation (non-decreasing over slots).
        t_last: ``(C,)`` int32 frame index of the last fusion into the surfel.
        alive: ``(C,)`` bool, False for removed slots.
    """

    FIELDS = ("pos", "normal", "radius", "color", "conf", "t_init", "t_last", "alive")

    def __init__(self, capacity: int = INITIAL_CAPACITY, chunk_size: int = CHUNK_SIZE,
                 growth_factor: float = GROWTH_FACTOR, compact_fraction: float = COMPACT_FRACTION,
                 device: str | torch.device = "cpu") -> None:
        if int(capacity) < 1 or int(chunk_size) < 64 or growth_factor <= 1 or not 0 < compact_fraction <= 1:
            raise ValueError("SurfelStore: need capacity >= 1, chunk_size >= 64, growth_factor > 1 and "
                             "compact_fraction in (0, 1]")
        self.device = torch.device(device)
        self.chunk_size = int(chunk_size)
        self.growth_factor = float(growth_factor)
        self.compact_fraction = float(compact_fraction)
        self.n = 0            # slots in use (alive or dead)
        self.num_dead = 0     # dead slots among [0, n)
        self.aged_upto = 0    # slots [0, aged_upto) have passed the unstable-window age check
        self.sorted_upto = 0  # slots [0, sorted_upto) were re-ordered spatially (see sort_aged)
        self.scratch: dict = {}   # persistent work buffers (index map, last fused view)
        self.version = 0      # bumped whenever slots move (compaction, re-ordering)
        self.edits = 0        # bumped by every change of contents (see ModelView.with_colour)
        self._alloc(max(int(capacity), self.chunk_size))

    # ------------------------------------------------------------------ storage
    def _alloc(self, capacity: int) -> None:
        capacity = int(math.ceil(capacity / self.chunk_size) * self.chunk_size)
        dev = self.device
        new = {
            "pos": torch.zeros(capacity, 3, device=dev),
            "normal": torch.zeros(capacity, 3, device=dev),
            "radius": torch.zeros(capacity, device=dev),
            "color": torch.zeros(capacity, 3, device=dev),
            "conf": torch.zeros(capacity, device=dev),
            "t_init": torch.zeros(capacity, dtype=torch.int32, device=dev),
            "t_last": torch.zeros(capacity, dtype=torch.int32, device=dev),
            "alive": torch.zeros(capacity, dtype=torch.bool, device=dev),
        }
        nchunks = capacity // self.chunk_size
        box_lo = torch.full((nchunks, 3), _INF, device=dev)
        box_hi = torch.full((nchunks, 3), -_INF, device=dev)
        if hasattr(self, "pos") and self.n > 0:
            for k in self.FIELDS:
                new[k][: self.n] = getattr(self, k)[: self.n]
            old_chunks = self.box_lo.shape[0]
            box_lo[:old_chunks] = self.box_lo
            box_hi[:old_chunks] = self.box_hi
        for k, v in new.items():
            setattr(self, k, v)
        self.box_lo, self.box_hi = box_lo, box_hi

    @property
    def capacity(self) -> int:
        return int(self.pos.shape[0])

    @property
    def num_alive(self) -> int:
        return self.n - self.num_dead

    def reserve(self, extra: int) -> None:
        """Make room for ``extra`` more slots, growing the capacity geometrically."""
        need = self.n + int(extra)
        if need > self.capacity:
            self._alloc(max(need, int(self.capacity * self.growth_factor)))

    # ------------------------------------------------------------------ edits
    def append(self, pos: torch.Tensor, normal: torch.Tensor, radius: torch.Tensor, color: torch.Tensor,
               conf: torch.Tensor, frame: int) -> torch.Tensor:
        """Append ``m`` surfels created at ``frame``; returns their slot indices ``(m,)`` int64."""
        m = int(pos.shape[0])
        if m == 0:
            return torch.zeros(0, dtype=torch.long, device=self.device)
        self.reserve(m)
        self.edits += 1
        s, e = self.n, self.n + m
        self.pos[s:e] = pos
        self.normal[s:e] = normal
        self.radius[s:e] = radius
        self.color[s:e] = color
        self.conf[s:e] = conf
        self.t_init[s:e] = frame
        self.t_last[s:e] = frame
        self.alive[s:e] = True
        self.n = e
        cs = self.chunk_size
        self.update_boxes(torch.arange(s // cs, (e - 1) // cs + 1, device=self.device))
        return torch.arange(s, e, device=self.device)

    def kill(self, slots: torch.Tensor) -> int:
        """Mark ``slots`` dead (duplicates / already dead ones are fine); returns how many died."""
        if slots.numel() == 0:
            return 0
        slots = take(slots, take(self.alive, slots).nonzero().squeeze(1)).unique()
        k = int(slots.numel())
        if k:
            self.edits += 1
            self.alive.index_fill_(0, slots, False)
            self.conf.index_fill_(0, slots, 0.0)
            self.num_dead += k
        return k

    def maybe_compact(self) -> bool:
        """Squeeze dead slots out once they exceed ``compact_fraction`` of the slots (order kept)."""
        # dead slots at the tail are dropped for free
        if self.num_dead and self.n and not bool(self.alive[self.n - 1]):
            last, end = 0, self.n
            while end > 0:                       # scan back one chunk at a time (usually one step)
                beg = max(0, end - self.chunk_size)
                nz = self.alive[beg:end].nonzero()
                if nz.numel():
                    last = beg + int(nz[-1, 0]) + 1
                    break
                end = beg
            self.num_dead -= self.n - last
            self.n = last
            self.aged_upto = min(self.aged_upto, self.n)
            self.sorted_upto = min(self.sorted_upto, self.n)
        if self.num_dead == 0 or self.num_dead < self.compact_fraction * self.n:
            return False
        self.compact()
        return True

    def compact(self) -> None:
        """Remove all dead slots now, keeping creation order; rebuilds the chunk boxes."""
        self.version += 1
        self.edits += 1
        n = self.n
        alive = self.alive[:n]
        keep = alive.nonzero().squeeze(1)
        m = int(keep.numel())
        self.aged_upto = int(alive[: self.aged_upto].sum())
        self.sorted_upto = int(alive[: self.sorted_upto].sum())
        for k in self.FIELDS:
            arr = getattr(self, k)
            arr[:m] = take(arr, keep)
            if k == "alive":
                arr[m:n] = False
        self.n = m
        self.num_dead = 0
        self.box_lo.fill_(_INF)
        self.box_hi.fill_(-_INF)
        if m:
            self.grow_boxes(torch.arange(m, device=self.device))

    def sort_aged(self, cell_mm: float, min_chunks: int = 16) -> bool:
        """Re-order the newest block of aged slots along a Z-order (Morton) curve of their positions.

        Slots are appended per frame in image order, and the unmatched pixels of a frame (surface
        entering the view, and a scatter of fill-ins) end up in chunks with wide boxes.  Once slots
        are past the unstable-window check (``< aged_upto``) their creation order no longer matters,
        so every ``min_chunks`` chunks of them are sorted spatially; each chunk then covers a compact
        patch and view culling stays tight.  Returns True when a block was sorted.
        """
        cs = self.chunk_size
        start = self.sorted_upto
        end = (self.aged_upto // cs) * cs
        if end - start < min_chunks * cs:
            return False
        self.version += 1
        self.edits += 1
        seg = torch.arange(start, end, device=self.device)
        p = self.pos[start:end]
        q = torch.floor((p - p.amin(0)) / cell_mm).long().clamp(0, (1 << 21) - 1)
        order = torch.argsort(_morton3(q[:, 0]) | (_morton3(q[:, 1]) << 1) | (_morton3(q[:, 2]) << 2))
        src = take(seg, order)
        for k in self.FIELDS:
            arr = getattr(self, k)
            arr[start:end] = take(arr, src)
        self.sorted_upto = end
        self.update_boxes(torch.arange(start // cs, (end - 1) // cs + 1, device=self.device))
        return True

    def update_boxes(self, chunks: torch.Tensor) -> None:
        """Recompute the bounding boxes of ``chunks`` (int64 chunk ids) from their live surfels."""
        if chunks.numel() == 0:
            return
        cs = self.chunk_size
        slots = (chunks[:, None] * cs + torch.arange(cs, device=self.device)).reshape(-1)
        live = take(self.alive, slots).view(-1, cs, 1)
        p = take(self.pos, slots).view(-1, cs, 3)
        r = take(self.radius, slots).view(-1, cs, 1)
        lo = torch.where(live, p - r, _INF).amin(dim=1)
        hi = torch.where(live, p + r, -_INF).amax(dim=1)
        self.box_lo[chunks] = lo
        self.box_hi[chunks] = hi

    def grow_boxes(self, slots: torch.Tensor) -> None:
        """Grow the boxes of the chunks holding ``slots`` to include those surfels (after they moved).

        Boxes only grow between compactions (they stay conservative); O(len(slots)).
        """
        if slots.numel() == 0:
            return
        p = take(self.pos, slots)
        r = take(self.radius, slots)[:, None]
        idx = ((slots // self.chunk_size) * 3)[:, None] + torch.arange(3, device=self.device)
        self.box_lo.view(-1).scatter_reduce_(0, idx.view(-1), (p - r).view(-1), reduce="amin")
        self.box_hi.view(-1).scatter_reduce_(0, idx.view(-1), (p + r).view(-1), reduce="amax")

    # ------------------------------------------------------------------ queries
    def chunk_candidates(self, chunk_mask: torch.Tensor) -> torch.Tensor:
        """Live slot indices of the chunks selected by ``chunk_mask`` (bool over used chunks)."""
        chunks = chunk_mask.nonzero().squeeze(1)
        if chunks.numel() == 0:
            return chunks
        cs = self.chunk_size
        slots = (chunks[:, None] * cs + torch.arange(cs, device=self.device)).reshape(-1)
        # slots >= n are never alive (invariant kept by append / kill / compact)
        return take(slots, take(self.alive, slots).nonzero().squeeze(1))

    @property
    def num_chunks(self) -> int:
        return (self.n + self.chunk_size - 1) // self.chunk_size

    def stable_mask(self, threshold: float) -> torch.Tensor:
        """``(n,)`` bool: alive and confidence >= threshold."""
        return self.alive[: self.n] & (self.conf[: self.n] >= threshold)
