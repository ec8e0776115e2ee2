"""A sweep store's manifest, ``DIR/manifest.json``: its schema, what it records, reading and checking it.

The manifest holds the schema, the canonical spec and its SHA-256, the digest of the values of the spec's preset
(:data:`PRESET_DIGEST`; the spec names the preset only), the chunk size, the device layout, the columns, and per
chunk its file, row range ``[start, stop)``, size, SHA-256 and wall time
(:func:`chunk_entry`). A store whose manifest names another sweep, schema or device layout is refused with
:class:`StoreMismatch` (:func:`check_manifest`); one that cannot be read is :class:`StoreCorrupt`
(:func:`read_manifest`). The store that keeps it is :class:`hyqjax.studies.sweep.store.SweepStore`.
"""
from __future__ import annotations

import datetime
import hashlib
import json
import os

from hyqjax.studies.sweep import legacy
from hyqjax.studies.sweep.legacy import OLD_SCHEMAS

#: The schema this hyqjax writes (Parquet chunks with content checksums); older ones: :data:`OLD_SCHEMAS`.
SCHEMA = "hyqjax.sweep/2"
MANIFEST = "manifest.json"


class StoreMismatch(RuntimeError):
    """The output directory holds a sweep of a different specification, schema, layout or version."""


class StoreCorrupt(RuntimeError):
    """A store file cannot be read (the message names it and what to do)."""


def now() -> str:
    """The current UTC time, to the second (ISO 8601), as the manifest records it."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def sha256_bytes(b: bytes) -> str:
    return hashlib.sha256(b).hexdigest()


def new_manifest(spec, chunk_size: int, layout: dict | None) -> dict:
    """The manifest of an empty store of ``spec`` in chunks of ``chunk_size`` on the device ``layout``."""
    from hyqjax.studies.stepdown import START_POSE

    cs = int(chunk_size)
    man = dict(schema=SCHEMA, start_pose=START_POSE, spec_hash=spec.spec_hash, spec=spec.to_dict(),
               n_instances=spec.n_instances, chunk_size=cs, n_chunks=-(-spec.n_instances // cs),
               layout=None if layout is None else dict(layout, chunk_size=cs), chunks={}, created=now())
    if spec.preset:  # the spec hash covers the preset's name; its values are recorded here
        man[PRESET_DIGEST] = preset_digest(spec.preset)
    return man


#: The manifest's record of the values of the spec's preset (:func:`preset_digest`).
PRESET_DIGEST = "preset_values_sha256"


def preset_digest(name: str) -> str:
    """SHA-256 of the canonical values JSON of preset ``name`` (:func:`hyqjax.presets.registry.values_digest`)."""
    from hyqjax.presets import registry

    return registry.get(name).digest


def check_preset_values(man: dict, out_dir: str) -> None:
    """Raise :class:`StoreMismatch` when the values of the spec's preset changed since the store recorded them (a
    manifest without the record, written before it was kept, passes)."""
    stored = man.get(PRESET_DIGEST)
    name = (man.get("spec") or {}).get("preset") or ""
    if not stored or not name:
        return
    now_digest = preset_digest(name)
    if now_digest != stored:
        raise StoreMismatch(
            f"{out_dir} was computed with other values of preset {name} (values sha256 {stored[:16]}; now "
            f"{now_digest[:16]}, `hyqjax presets {name}`), so it is not resumed (a store never mixes two parameter "
            f"sets); its rows read as they are: use another --out, or restore the preset's values")


def read_manifest(out_dir: str) -> dict | None:
    """The manifest of the store in ``out_dir``; None when it has none; :class:`StoreCorrupt` when it does not read
    as one."""
    path = os.path.join(out_dir, MANIFEST)
    try:
        with open(path, "rb") as f:
            man = json.loads(f.read().decode("utf-8"))
        if not isinstance(man, dict) or not isinstance(man.get("chunks"), dict):
            raise ValueError("not a sweep manifest (no 'chunks' table)")
        return man
    except FileNotFoundError:
        return None
    except (ValueError, UnicodeDecodeError) as e:
        raise StoreCorrupt(f"{path} is corrupt ({str(e)[:120]}); run the same `hyqjax sweep` command "
                           f"again to rebuild it from the chunk files, or remove {out_dir}") from None


def check_manifest(man: dict, out_dir: str, spec_hash: str, writer: bool, chunk_size: int | None,
                   layout: dict | None) -> None:
    """Raise :class:`StoreMismatch` unless the manifest ``man`` of ``out_dir`` is of this schema, this sweep
    (``spec_hash``) and the device ``layout`` (None: not checked); a writer is also refused on a converted
    store, on one of another start pose (:data:`hyqjax.studies.stepdown.START_POSE`; ``hip-line`` when not
    recorded) and on one whose spec's preset has other values now than it recorded (:func:`check_preset_values`). An old schema's store of the same sweep passes (read as it is, never resumed)."""
    path = os.path.join(out_dir, MANIFEST)
    if man.get("schema") in OLD_SCHEMAS:  # same spec, read as is, never resumed
        why = legacy.v1_refusal(out_dir, man, spec_hash, writer)
        if why:
            raise StoreMismatch(why)
        return
    if man.get("schema") != SCHEMA:
        raise StoreMismatch(f"{path} has schema {man.get('schema')!r}, expected {SCHEMA!r}")
    if man.get("spec_hash") != spec_hash:
        raise StoreMismatch(
            f"{out_dir} holds a different sweep (spec hash {str(man.get('spec_hash', '?'))[:12]}, this spec "
            f"{spec_hash[:12]}); use another --out directory or remove {out_dir}")
    if writer and man.get("converted_from"):
        raise StoreMismatch(legacy.read_only_message(out_dir, man["converted_from"], converted=True))
    if writer:
        from hyqjax.studies.stepdown import START_POSE, recorded_start_pose

        pose = recorded_start_pose(man)
        if pose != START_POSE:
            raise StoreMismatch(
                f"{out_dir} was computed with the {pose!r} start pose (this hyqjax starts the step-down with the "
                f"{START_POSE!r} pose: hyqjax.studies.stepdown.start_qpos), so it is not resumed (a store never "
                f"mixes two start poses); its rows read as they are: use another --out")
        check_preset_values(man, out_dir)
    if chunk_size is not None and chunk_size != man["chunk_size"]:
        print(f"note: resuming with the stored chunk size {man['chunk_size']} (ignoring {chunk_size})")
    stored = man.get("layout")
    if layout is not None and stored is not None:
        want = dict(layout, chunk_size=man["chunk_size"])
        stored = dict(stored, impl=stored.get("impl", "jax"))  # stores written before impl was recorded
        want.setdefault("impl", "jax")
        keys = ("platform", "device_kind", "devices", "chunk_size", "impl")
        if any(stored.get(k) != want.get(k) for k in keys):
            fmt = lambda lo: (f"{lo.get('devices')} x {lo.get('device_kind')} ({lo.get('platform')}), "  # noqa: E731
                              f"chunks of {lo.get('chunk_size')}, MJX impl {lo.get('impl')}")
            raise StoreMismatch(
                f"{out_dir} was computed on {fmt(stored)}; this run has {fmt(want)}. An instance's result "
                f"depends on the batch each device compiles for, so a store never mixes layouts: resume "
                f"with the same devices (e.g. CUDA_VISIBLE_DEVICES / --executor), or use another --out")


def chunk_entry(file: str, start: int, stop: int, data: bytes, wall_s=None, worker=None, adopted=False) -> dict:
    """The manifest's record of a chunk: its ``file`` (relative to the store), row range, the size and SHA-256 of
    its bytes ``data``, wall time, and the worker that computed it (or ``adopted``: recorded after its writer
    stopped)."""
    e = dict(file=file, start=start, stop=stop, rows=stop - start, bytes=len(data), sha256=sha256_bytes(data),
             wall_s=None if wall_s is None else round(wall_s, 3), finished=now())
    if worker:
        e["worker"] = worker
    if adopted:
        e["adopted"] = True
    return e
