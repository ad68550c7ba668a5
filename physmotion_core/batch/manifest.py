"""Job records and the batch manifest.

Each job's folder ``OUT/<id>/`` holds its outputs and ``record.json``, written (atomically) after
every output: the record is the job's commit point. It lists each output's SHA-256 and size, so
a rerun trusts a finished job only if its files are all there and unchanged. The manifest
(``OUT/manifest.jsonl``, and ``OUT/manifest.parquet`` when pyarrow is installed) is rebuilt from
the records, one row per job of the spec in spec order, and rewritten atomically as jobs finish.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

from ..fsutil import atomic_output
from .job import sha256_file

RECORD = "record.json"


def job_dir(out: Path, job_id: str) -> Path:
    return Path(out) / job_id


def read_record(out: Path, job_id: str) -> Optional[dict]:
    try:
        rec = json.loads((job_dir(out, job_id) / RECORD).read_text())
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) and rec.get("id") == job_id else None


def write_record(out: Path, record: dict) -> None:
    path = job_dir(out, record["id"]) / RECORD
    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(record, indent=1, default=str))


def verify(out: Path, record: dict) -> tuple[bool, str]:
    """Whether every output the record lists is on disk with its recorded size and digest."""
    base = job_dir(out, record["id"])
    files = record.get("files") or {}
    if not files:
        return False, "the record lists no outputs"
    for rel, info in files.items():
        p = base / rel
        try:
            size = p.stat().st_size
        except OSError:
            return False, f"{rel} is missing"
        if size != info.get("bytes") or sha256_file(p) != info.get("sha256"):
            return False, f"{rel} has changed since it was written (size or SHA-256 differs)"
    return True, ""


def clean_partial(out: Path, job_id: str) -> None:
    """Remove what an unfinished attempt left: temporary files of atomic writers, the running marker."""
    base = job_dir(out, job_id)
    if not base.is_dir():
        return
    for p in list(base.rglob(".*")):
        if p.is_file() and (p.name == ".running" or ".tmp" in p.name):
            try:
                p.unlink()
            except OSError:
                pass


def manifest_row(job, record: Optional[dict], out: Path) -> dict:
    """One manifest row: inputs, settings, status and error, physics stats, timings, outputs."""
    row = {"id": job.id, "name": job.name, "index": job.index, "image": str(job.image), "image_sha256": job.image_sha256,
           "settings": job.settings, "sets": job.sets or None, "status": "pending"}
    if record is None:
        return row
    row.update({k: record.get(k) for k in ("status", "error", "attempts", "physics_version", "executor", "host",
                                           "stats", "stages", "timings", "job_s", "frames", "size", "skipped", "warnings",
                                           "finished_at", "versions")})
    files = record.get("files") or {}
    video = record.get("video") if record.get("status") == "done" else None
    row["video"] = f"{job.id}/{video}" if video else None
    row["video_sha256"] = (files.get(video) or {}).get("sha256") if video else None
    row["outputs"] = sorted(files)
    return row


def _flat(row: dict) -> dict:
    """A row with one column per leaf value (dicts flattened with dots; lists of tables as JSON text),
    for Parquet."""
    out = {}

    def put(prefix, value):
        if isinstance(value, dict):
            if not value:
                out[prefix] = None
            for k, v in value.items():
                put(f"{prefix}.{k}" if prefix else k, v)
        elif isinstance(value, list) and value and not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                             for v in value):
            out[prefix] = json.dumps(value, default=str)
        elif isinstance(value, list):
            out[prefix] = [float(v) for v in value] if value else None
        else:
            out[prefix] = value

    put("", row)
    return out


def write_manifest(out: Path, rows: list[dict]) -> list[Path]:
    out = Path(out)
    written = []
    path = out / "manifest.jsonl"
    with atomic_output(path) as tmp:
        with open(tmp, "w") as fh:
            for r in rows:
                fh.write(json.dumps(r, default=str, sort_keys=False) + "\n")
    written.append(path)
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ModuleNotFoundError:
        return written
    flat = [_flat(r) for r in rows]
    columns = sorted({k for r in flat for k in r})
    data = {}
    for c in columns:
        values = [r.get(c) for r in flat]
        kinds = {type(v) for v in values if v is not None}
        if len(kinds) > 1 and not kinds <= {int, float}:
            values = [None if v is None else json.dumps(v, default=str) for v in values]  # mixed: text
        elif kinds == {int, float}:
            values = [None if v is None else float(v) for v in values]
        data[c] = values
    table = pa.table(data)
    ppath = out / "manifest.parquet"
    with atomic_output(ppath, suffix=".tmp.parquet") as tmp:
        pq.write_table(table, str(tmp))
    written.append(ppath)
    return written


def read_manifest(out: Path) -> list[dict]:
    path = Path(out) / "manifest.jsonl"
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if line:
            rows.append(json.loads(line))
    return rows


def append_log(out: Path, line: str) -> None:
    """One line of OUT/batch.log (appended in one write, so lines from one run never interleave)."""
    fd = os.open(Path(out) / "batch.log", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    try:
        os.write(fd, (line.rstrip("\n") + "\n").encode())
    finally:
        os.close(fd)
