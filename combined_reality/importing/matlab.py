"""MATLAB .mat files: v4 to v7 through scipy.io, v7.3 (HDF5) through h5py (the `mat73` extra).

A channel is a variable (`Zeit`), a field of a struct (`run.t`, any depth) or a column of a
matrix in MATLAB's own notation, one-based (`data(:,3)`); each must hold one value per sample."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .mapping import ImportMapping, MappingError
from .raw import RawTable, optional_reader, require_column_time, require_file, require_finite

__all__ = ["read_mat"]

_COLUMN = re.compile(r"^(?P<var>[^()]+)\(\s*:\s*,\s*(?P<col>\d+)\s*\)$")


def read_mat(path: Path, mapping: ImportMapping) -> RawTable:
    require_column_time(mapping, "variable")
    require_file(path)
    lookup, version = _open(path)
    by_source = {name: _channel(path, lookup, name) for name in mapping.source_names()}
    lengths = {n: v.size for n, v in by_source.items()}
    if len(set(lengths.values())) > 1:
        shown = ", ".join(f"{n!r} {k}" for n, k in lengths.items())
        raise MappingError(f"{path}: the mapped variables differ in length ({shown}); each needs one value per sample.")
    n = next(iter(lengths.values()))
    if n < 2:
        raise MappingError(f"{path}: {n} sample(s); a run needs at least 2.")
    columns = {ch.name: by_source[ch.source] for ch in mapping.channels}
    require_finite(path, columns, _sample)
    return RawTable(columns=columns, locate=_sample, describe=f"MATLAB {version} file, {n} samples")


def _sample(i: int) -> str:
    return f"sample {i + 1}"


def _open(path: Path):
    """A function name -> array (MATLAB orientation), and the file's version."""
    import scipy.io

    try:
        data = scipy.io.loadmat(path, squeeze_me=False, struct_as_record=True, simplify_cells=True)
    except NotImplementedError:  # v7.3: HDF5
        h5py = optional_reader("h5py", "mat73", "MATLAB v7.3 files")
        try:
            f = h5py.File(path, "r")
        except OSError as e:
            raise MappingError(f"{path}: not a readable MATLAB v7.3 (HDF5) file ({e}).") from None

        def get73(parts: list[str]):
            node = f
            for p in parts:
                if not isinstance(node, h5py.Group) or p not in node:
                    return None
                node = node[p]
            if not isinstance(node, h5py.Dataset):
                return None
            return np.asarray(node[()]).T  # HDF5 stores MATLAB's column-major arrays transposed

        return get73, "v7.3"
    except (ValueError, TypeError, OSError, KeyError, IndexError, EOFError) as e:
        raise MappingError(f"{path}: not a readable MATLAB file ({str(e).splitlines()[0] if str(e) else e}).") \
            from None

    def get(parts: list[str]):
        node = data
        for p in parts:
            if not isinstance(node, dict) or p not in node:
                return None
            node = node[p]
        return node

    return get, "v5"


def _channel(path: Path, lookup, name: str) -> np.ndarray:
    m = _COLUMN.match(name)
    var, col = (m.group("var").strip(), int(m.group("col"))) if m else (name, None)
    value = lookup(var.split("."))
    if value is None:
        raise MappingError(f"{path}: no variable '{var}' (name variables, struct fields as run.t, or matrix columns "
                           f"as data(:,3)).")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise MappingError(f"{path}: variable '{var}' does not hold numbers.") from None
    if col is not None:
        if arr.ndim != 2 or not 1 <= col <= arr.shape[1]:
            raise MappingError(f"{path}: '{name}' asks for column {col}, but '{var}' has shape {arr.shape}.")
        arr = arr[:, col - 1]
    arr = np.squeeze(arr)
    if arr.ndim != 1:
        raise MappingError(f"{path}: '{name}' has shape {np.shape(value)}, not one value per sample (pick a column "
                           f"as {var}(:,k)).")
    return arr
