"""Batches of pairs for training and evaluation, made ahead on a background thread.

Batches are built by :meth:`PairDataset.batch` (vectorised numpy, which releases the GIL for most of its work)
while the accelerator runs the previous step; ``prefetch`` batches wait in a queue.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator

import numpy as np

from dit_jax.data.pairs import PairDataset


def epoch_order(n_pairs: int, epoch: int, seed: int, shuffle: bool) -> np.ndarray:
    """The order of pair indices in an epoch: a permutation seeded by (seed, epoch), or 0..n-1."""
    if not shuffle:
        return np.arange(n_pairs)
    return np.random.default_rng([seed, epoch, 0x5EED]).permutation(n_pairs)


def batches(
    dataset: PairDataset,
    batch_size: int,
    *,
    epoch: int = 0,
    shuffle: bool | None = None,
    drop_remainder: bool | None = None,
    start_batch: int = 0,
    prefetch: int = 2,
    seed: int | None = None,
) -> Iterator[dict[str, np.ndarray]]:
    """Yields the batches of one epoch, ``batch_size`` pairs each.

    Args:
      dataset: the pairs.
      batch_size: pairs per batch.
      epoch: which epoch (training pairs and their order change with it).
      shuffle: shuffle the order (default: for training pairs).
      drop_remainder: drop a last, smaller batch (default: for training pairs, so shapes stay fixed).
      start_batch: skip this many batches (to resume inside an epoch).
      prefetch: batches made ahead on a background thread (0: none).
      seed: of the order (default: the dataset's seed).
    """
    train = dataset.config.train
    shuffle = train if shuffle is None else shuffle
    drop_remainder = train if drop_remainder is None else drop_remainder
    order = epoch_order(len(dataset), epoch, dataset.config.seed if seed is None else seed, shuffle)
    stop = len(order) - len(order) % batch_size if drop_remainder else len(order)
    starts = range(start_batch * batch_size, stop, batch_size)
    make = lambda s: dataset.batch(order[s : s + batch_size], epoch)
    if prefetch <= 0:
        for s in starts:
            yield make(s)
        return
    yield from _prefetched((make(s) for s in starts), prefetch)


_DONE = object()


def _prefetched(items: Iterator, size: int) -> Iterator:
    q: queue.Queue = queue.Queue(maxsize=size)
    stop = threading.Event()

    def work():
        try:
            for item in items:
                while not stop.is_set():
                    try:
                        q.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put(_DONE)
        except BaseException as err:  # hand the producer's error to the consumer
            q.put(err)

    thread = threading.Thread(target=work, daemon=True)
    thread.start()
    try:
        while True:
            item = q.get()
            if item is _DONE:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
