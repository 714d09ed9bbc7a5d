"""Model files that are safe to load: JSON for plain data, tensors for the rest.

A model file is a zip archive holding ``cme_agent.json`` (hyperparameters, spaces, counters,
the numpy RNG state: plain JSON) and ``tensors.pt`` (state dicts and other tensors, read with
``torch.load(weights_only=True)``). Nothing in it is unpickled as arbitrary objects, so loading
a file never runs code carried in it; a file that tries is refused. Files are written to a
temporary name and renamed into place, so a crash never leaves a half-written file.
"""

from __future__ import annotations

import io
import json
import os
import pathlib
import pickle
import secrets
import zipfile
from typing import Any

import numpy as np
import torch
from gymnasium import spaces

FORMAT = "cme_agent.model/2"
META = "cme_agent.json"
TENSORS = "tensors.pt"


class ModelFileError(ValueError):
    """A file that is not a readable cme_agent model file, or that was refused as unsafe."""


def space_to_dict(space: spaces.Space) -> dict[str, Any]:
    """A Box or Discrete space as plain JSON data."""
    if isinstance(space, spaces.Discrete):
        return {"type": "Discrete", "n": int(space.n), "start": int(space.start)}
    if isinstance(space, spaces.Box):
        return {"type": "Box", "low": space.low.tolist(), "high": space.high.tolist(), "dtype": str(space.dtype)}
    raise TypeError(f"cannot save space {space}")


def space_from_dict(data: dict[str, Any]) -> spaces.Space:
    """Inverse of :func:`space_to_dict`."""
    if data.get("type") == "Discrete":
        return spaces.Discrete(data["n"], start=data.get("start", 0))
    if data.get("type") == "Box":
        dtype = np.dtype(data["dtype"])
        return spaces.Box(np.array(data["low"], dtype=dtype), np.array(data["high"], dtype=dtype), dtype=dtype)
    raise ModelFileError(f"unknown space description {data!r}")


def model_path(path: str | pathlib.Path) -> pathlib.Path:
    """SB3's convention: a path without a suffix gets ``.zip``."""
    path = pathlib.Path(path)
    return path if path.suffix else path.with_suffix(".zip")


def write_atomically(path: str | pathlib.Path, members: dict[str, bytes]) -> None:
    """Write a zip of ``members`` to ``path`` through a temporary file in the same folder and a rename.

    The temporary file is created with mode 0666 less the process umask (``tempfile.mkstemp``
    would make it 0600), so the file gets the permissions of any file the user writes.

    :param path: destination; its folder is created if needed
    :param members: archive member name -> content
    """
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    while True:
        temporary = path.parent / f".{path.name}.{secrets.token_hex(8)}.tmp"
        try:
            handle = os.open(temporary, flags, 0o666)  # the kernel applies the umask
            break
        except FileExistsError:  # a name already taken: draw another
            continue
    try:
        with os.fdopen(handle, "wb") as raw, zipfile.ZipFile(raw, "w", zipfile.ZIP_DEFLATED) as archive:
            for name, content in members.items():
                archive.writestr(name, content)
            archive.close()
            raw.flush()
            os.fsync(raw.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def read_members(path: str | pathlib.Path | io.BufferedIOBase, names: tuple[str, ...]) -> dict[str, bytes]:
    """Read ``names`` from a model archive, with a clear error for anything else.

    :raises ModelFileError: missing, truncated or foreign file
    """
    source: Any = path
    if isinstance(path, (str, pathlib.Path)):
        source = pathlib.Path(path)
        if not source.exists() and not source.suffix:
            source = source.with_suffix(".zip")
        if not source.exists():
            raise ModelFileError(f"no model file at {path}")
    try:
        with zipfile.ZipFile(source) as archive:
            missing = [name for name in names if name not in archive.namelist()]
            if missing:
                raise ModelFileError(f"{path} is not a cme_agent model file (no {', '.join(missing)})")
            return {name: archive.read(name) for name in names}
    except (zipfile.BadZipFile, EOFError, OSError, zipfile.LargeZipFile) as error:
        raise ModelFileError(f"{path} is not a readable cme_agent model file (truncated or not a zip): {error}") from error


def tensors_to_bytes(tensors: dict[str, Any]) -> bytes:
    """Serialise a nested dict of tensors and plain numbers with ``torch.save``."""
    buffer = io.BytesIO()
    torch.save(tensors, buffer)
    return buffer.getvalue()


def tensors_from_bytes(content: bytes, device: torch.device | str = "cpu") -> dict[str, Any]:
    """Inverse of :func:`tensors_to_bytes` with ``weights_only=True``: objects other than
    tensors and plain containers are refused, never constructed.

    :raises ModelFileError: the content holds anything else, or is corrupt
    """
    try:
        return torch.load(io.BytesIO(content), map_location=device, weights_only=True)
    except pickle.UnpicklingError as error:
        raise ModelFileError(
            f"refused to load: the file holds objects other than tensors, which could run code ({error})"
        ) from error
    except (RuntimeError, EOFError, ValueError) as error:
        raise ModelFileError(f"the tensors of the model file are corrupt: {error}") from error


def meta_from_bytes(content: bytes) -> dict[str, Any]:
    """Parse and check ``cme_agent.json``."""
    try:
        meta = json.loads(content)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ModelFileError(f"corrupt {META}: {error}") from error
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ModelFileError(
            f"unsupported model format {meta.get('format') if isinstance(meta, dict) else meta!r}; expected {FORMAT}"
        )
    return meta
