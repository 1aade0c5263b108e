"""Resuming a hide: finished parts (or blocks) of noise in OUT.partial/, for one run at a time."""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
from pathlib import Path
from typing import Callable

import torch
from safetensors import safe_open
from safetensors.torch import save

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import existing_kind, write_bytes


class ResumeStore:
    """Finished parts of noise in OUT.partial/, for one run at a time.

    A run holds an exclusive lock on OUT.partial/lock for its whole life, so a second hide writing to the
    same output is refused at once instead of mixing two secrets' parts. Each part is written atomically
    (fsynced, then renamed) and carries the run key, its own position and a SHA-256 of its tensors; a
    part that fails any check on load (another run's, truncated, edited, wrong shape or dtype, NaN,
    missing fields, a dtype or value the solver does not expect) is deleted and solved again. The key file says which run the folder belongs to; if it
    is anything but this run's key in a regular file, every part there is discarded.
    """

    def __init__(self, output: Path, key: str):
        self.directory = output.with_name(output.name + ".partial")
        self.key = key
        if existing_kind(self.directory) not in (None, "a directory"):
            raise UserError(f"the resume folder {self.directory} is {existing_kind(self.directory)}; remove it")
        try:
            self.directory.mkdir(exist_ok=True)
            self.lock = os.open(self.directory / "lock", os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
        except OSError as error:
            raise UserError(f"cannot use the resume folder {self.directory}: {error.strerror or error}") from None
        try:
            fcntl.flock(self.lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            if not self.owns_folder():
                self.discard_all()
            write_bytes(self.directory / "key", key.encode(), replace=True)
        except BlockingIOError:
            os.close(self.lock)
            raise UserError(f"another hide is writing to {self.directory}; wait for it or choose another -o") from None
        except BaseException:
            os.close(self.lock)  # a failed start must not keep the folder locked (in-process callers go on)
            raise

    def owns_folder(self) -> bool:
        """Whether the folder's key file is a regular file holding this run's key."""
        key_file = self.directory / "key"
        if existing_kind(key_file) != "a file":
            return False
        with open(key_file, "rb") as handle:
            return handle.read(len(self.key) + 1) == self.key.encode()

    def discard_all(self) -> None:
        """Remove everything in the folder but the lock we hold (another run's parts, a stray key folder)."""
        for entry in self.directory.iterdir():
            if entry.name != "lock":
                remove(entry)

    def path(self, tile: int, part: int) -> Path:
        return self.directory / f"tile{tile:04d}_part{part:05d}.safetensors"

    def stamp(self, tile: int, part: int, tensors: dict[str, torch.Tensor]) -> dict[str, str]:
        """What a part must carry to be reused: this run, this place, and a digest of exactly these tensors."""
        digest = hashlib.sha256(f"{self.key}/{tile}/{part}".encode())
        for name in sorted(tensors):
            value = tensors[name].contiguous().cpu()
            digest.update(f"{name}:{value.dtype}:{tuple(value.shape)}".encode())
            digest.update(value.view(torch.uint8).numpy().tobytes() if value.numel() else b"")
        return {"run_key": self.key, "tile": str(tile), "part": str(part), "sha256": digest.hexdigest()}

    def load(self, tile: int, part: int, layout: dict[str, tuple[tuple[int, ...], torch.dtype]],
             sound: Callable[[dict[str, torch.Tensor]], bool] = lambda tensors: True) -> dict | None:
        """A saved part that passes every check, else None: exactly the tensors `layout` names with its
        (shape, dtype), finite, and `sound` by the solver's own assumptions. A part that fails is deleted,
        so it is solved again and rewritten."""
        path = self.path(tile, part)
        if existing_kind(path) is None:
            return None
        tensors = self.verified(path, tile, part, layout)
        if tensors is None or not sound(tensors):
            remove(path)
            return None
        return tensors

    def verified(self, path: Path, tile: int, part: int, layout: dict) -> dict | None:
        """The part's tensors if its stamp, shapes, dtypes and values are sound; None for anything else."""
        try:
            with safe_open(str(path), framework="pt") as handle:
                metadata = handle.metadata() or {}
                tensors = {name: handle.get_tensor(name) for name in handle.keys()}
        except Exception:  # safetensors raises several types for bad files; any of them means "recompute"
            return None
        if metadata != self.stamp(tile, part, tensors):
            return None
        if {name: (tuple(value.shape), value.dtype) for name, value in tensors.items()} != layout:
            return None
        if any(value.is_floating_point() and not torch.isfinite(value).all() for value in tensors.values()):
            return None
        return tensors

    def discard(self, tile: int, part: int) -> None:
        """Delete a saved part (one its tile's check showed to be wrong), so no resume takes it again."""
        remove(self.path(tile, part))

    def save(self, tile: int, part: int, tensors: dict) -> None:
        tensors = {k: v.contiguous().cpu() for k, v in tensors.items()}
        write_bytes(self.path(tile, part), save(tensors, metadata=self.stamp(tile, part, tensors)), replace=True)

    def clear(self) -> None:
        """Remove the folder once the bundle is written (the lock is released on leaving the run)."""
        shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self) -> "ResumeStore":
        return self

    def __exit__(self, *exc) -> None:
        os.close(self.lock)  # releases the flock, whether the run finished or failed


def remove(entry: Path) -> None:
    """Delete a file, symlink or folder in OUT.partial/ (a folder where a part or the key should be)."""
    if existing_kind(entry) == "a directory":
        shutil.rmtree(entry)
    else:
        entry.unlink(missing_ok=True)
