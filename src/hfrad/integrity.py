"""Integrity of hfrad's HDF5 files: the form-factor cache, HF checkpoints and ``.hfr`` files.

Every non-empty array dataset carries HDF5's Fletcher-32 checksum on each chunk
(:func:`checked_dataset`; HDF5 checks it as the data are read), the root a
SHA-256 digest of every attribute (:data:`DIGEST`) and the list of datasets
(:data:`MANIFEST`), both written last by :func:`seal`; :func:`integrity_problem`
says in words what is wrong with a file, or None. A base module: the cache
(layer 2), checkpoints (3) and ``.hfr`` files (4) all use it, and none of them
owns it.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np

__all__ = ["DIGEST", "MANIFEST", "checked_dataset", "dataset_names", "attrs_digest", "seal", "integrity_problem"]

#: Root attribute holding the SHA-256 digest of every attribute of the file.
DIGEST = "attrs_sha256"
#: Root attribute listing every dataset of the file (JSON), so a deleted one is noticed.
MANIFEST = "datasets"


def checked_dataset(g, name: str, data=None, **kwargs):
    """Create dataset ``name`` in ``g`` with HDF5's Fletcher-32 checksum on each chunk.

    ``data`` or ``shape``/``dtype`` (keywords of ``create_dataset``). An empty
    or scalar array is stored unchunked, without a checksum (nothing to check).
    """
    if data is not None:
        a = np.asarray(data)
        if a.size and a.ndim:
            return g.create_dataset(name, data=a, fletcher32=True, chunks=kwargs.pop("chunks", True), **kwargs)
        return g.create_dataset(name, data=a, **kwargs)
    shape = kwargs.pop("shape")
    if int(np.prod(shape)) and len(shape):
        return g.create_dataset(name, shape=shape, fletcher32=True, chunks=kwargs.pop("chunks", None) or True,
                                **kwargs)
    return g.create_dataset(name, shape=shape, **kwargs)


def dataset_names(f) -> list[str]:
    """The paths of every dataset in an open HDF5 file, sorted."""
    import h5py

    names: list[str] = []
    f.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset) else None)
    return sorted(names)


def attrs_digest(f) -> str:
    """SHA-256 over every attribute of every group (as stored), except the digest itself."""
    import h5py

    h = hashlib.sha256()
    groups = []
    f.visititems(lambda name, obj: groups.append((name, obj)) if isinstance(obj, h5py.Group) else None)
    for name, obj in [("/", f), *sorted(groups, key=lambda t: t[0])]:
        for key in sorted(obj.attrs):
            if obj is f and key == DIGEST:
                continue
            value = np.asarray(obj.attrs[key])
            h.update(f"{name}/{key}:{value.dtype.str}:{value.shape}:".encode())
            h.update(value.tobytes() if value.dtype.kind != "O" else repr(value.tolist()).encode())
    return h.hexdigest()


def seal(f) -> None:
    """Record the dataset manifest and the attributes' digest (call last, before closing)."""
    f.attrs[MANIFEST] = json.dumps(dataset_names(f))
    f.attrs[DIGEST] = attrs_digest(f)


def integrity_problem(f, *, manifest_required: bool = True, may_be_missing=()) -> str | None:
    """What is wrong with a file written with :func:`checked_dataset` and :func:`seal`, or None.

    Checks that the digest is there and matches, that the datasets are those
    of the manifest (when present; required unless ``manifest_required`` is
    False) and that each non-empty array dataset carries its checksum (the
    data themselves are checked by HDF5 as they are read). Neither check can
    be passed by deleting what it checks. ``may_be_missing``: datasets the
    reader recomputes when absent (a listed one that is gone is no damage).
    """
    if DIGEST not in f.attrs:
        return "its attribute digest is missing (damaged or edited file)"
    if str(f.attrs[DIGEST]) != attrs_digest(f):
        return "its header attributes are damaged (their SHA-256 digest does not match)"
    names = dataset_names(f)
    if MANIFEST in f.attrs:
        listed = json.loads(f.attrs[MANIFEST])
        missing = sorted(set(listed) - set(names) - set(may_be_missing))
        extra = sorted(set(names) - set(listed))
        if missing or extra:
            return ("its datasets differ from those it was written with"
                    + (f"; missing: {', '.join(missing[:5])}" if missing else "")
                    + (f"; unexpected: {', '.join(extra[:5])}" if extra else ""))
    elif manifest_required:
        return "its list of datasets is missing (damaged or edited file)"
    for name in names:
        ds = f[name]
        if ds.size and ds.ndim and not ds.fletcher32:
            return f"dataset /{name} has no checksum (damaged or edited file)"
    return None
