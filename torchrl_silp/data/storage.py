"""Replay-buffer checkpoints that hold what a buffer contains, not the capacity it preallocated."""

from __future__ import annotations

import json
from pathlib import Path

from tensordict import TensorDict, is_tensor_collection
from torchrl.data.replay_buffers.checkpointers import TensorStorageCheckpointer

__all__ = ["FilledStorageCheckpointer"]


class FilledStorageCheckpointer(TensorStorageCheckpointer):
    """A TorchRL storage checkpointer that writes only the filled rows of a 1-D TensorDict storage.

    TorchRL's :class:`~torchrl.data.replay_buffers.checkpointers.TensorStorageCheckpointer`
    memory-maps the whole ``LazyTensorStorage``: a 500k-transition buffer is written at its full
    capacity after a thousand frames. This one writes rows ``[0, len(storage))`` in storage order
    (so a circular buffer's cursor, kept by the writer's own checkpoint, still points at the
    oldest row) and on load allocates the storage at its capacity and fills those rows. Give it to
    the buffer (``ReplayBuffer(..., checkpointer=FilledStorageCheckpointer())``, which sets it on
    the storage); ``ReplayBuffer.dumps`` / ``loads`` then use it. It also loads a checkpoint that
    TorchRL's own checkpointer wrote.

    Examples:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from pathlib import Path
        >>> def buffer():
        ...     return TensorDictReplayBuffer(storage=LazyTensorStorage(100_000), checkpointer=FilledStorageCheckpointer())
        >>> rb = buffer()
        >>> _ = rb.extend(TensorDict({"x": torch.arange(10.0)}, [10]))
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     rb.dumps(tmp)
        ...     stored = (Path(tmp) / "storage" / "x.memmap").stat().st_size  # 10 float32 rows, not 100_000
        ...     restored = buffer()
        ...     restored.loads(tmp)
        >>> stored, len(restored), restored.storage.max_size, restored.storage[:10]["x"].sum().item()
        (40, 10, 100000, 45.0)
    """

    def dumps(self, storage, path):
        path = Path(path)
        path.mkdir(exist_ok=True)
        if not storage.initialized:
            raise RuntimeError("Cannot save a non-initialized storage.")
        n = len(storage)
        data = storage[:n]
        if not is_tensor_collection(data) or data.batch_dims < 1:
            raise TypeError(f"FilledStorageCheckpointer saves TensorDict storages, got {type(data).__name__}")
        data.memmap(path, copy_existing=True)
        (path / "storage_metadata.json").write_text(json.dumps({"len": n, "filled_rows_only": True}))

    def loads(self, storage, path):
        path = Path(path)
        meta = json.loads((path / "storage_metadata.json").read_text())
        if not meta.get("filled_rows_only"):  # a checkpoint TorchRL's own checkpointer wrote
            return super().loads(storage, path)
        n = meta["len"]
        if n > storage.max_size:
            raise ValueError(f"the checkpoint holds {n} rows, more than the storage's capacity {storage.max_size}")
        saved = TensorDict.load_memmap(path)
        if n:
            storage[:n] = saved  # allocates a lazy storage at its capacity first
        # the storage holds the checkpoint's rows, however many it held before (tests/test_demo_buffer.py);
        # TorchRL's own checkpointers assign the length the same way
        storage._len = n  # private: no public API sets a storage's length

