"""`cv2x-marl simulate`: one stage-1 run, written as links table, summary and figure."""

from __future__ import annotations

import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import cv2x_marl
from cv2x_marl.config import ScenarioConfig, apply_overrides, to_dict
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.runs import run_folder
from cv2x_marl.sim import Simulator
from cv2x_marl.sim.chunk import LINK_COLUMNS
from cv2x_marl.sim.memory import LINK_ROW_BYTES, estimate_memory_bytes


def links_table(links: dict[str, np.ndarray]) -> pa.Table:
    """The links columns as an Arrow table."""
    return pa.table({k: pa.array(v) for k, v in links.items()})


def write_parquet(table: pa.Table, path: Path) -> Path:
    """Write a parquet file atomically."""
    return atomic_write(path, lambda p: pq.write_table(table, p))


#: rows buffered before a row group of the streamed links table is written (bounded memory)
ROW_GROUP_ROWS = 1 << 20


class LinksWriter:
    """The links table written as the run goes: row groups of :data:`ROW_GROUP_ROWS` rows into a
    temporary file next to ``path``, renamed to ``path`` by :meth:`close` (atomic: a failed run
    leaves no partial ``links.parquet``). Use as the simulator's ``links_sink``."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.name}.tmp")
        self.rows = 0
        self._parts: list[pa.Table] = []
        self._buffered = 0
        self._writer: pq.ParquetWriter | None = None

    def __call__(self, chunk: dict[str, np.ndarray]) -> None:
        table = links_table(chunk)
        self._parts.append(table)
        self._buffered += table.num_rows
        self.rows += table.num_rows
        if self._buffered >= ROW_GROUP_ROWS:
            self._flush()

    def _flush(self) -> None:
        if not self._parts:
            return
        table = pa.concat_tables(self._parts)
        if self._writer is None:
            self._writer = pq.ParquetWriter(self.tmp, table.schema)
        self._writer.write_table(table, row_group_size=max(table.num_rows, 1))
        self._parts, self._buffered = [], 0

    def close(self, empty: dict[str, np.ndarray]) -> Path:
        """Finish the file (``empty``: the columns of a run without a single link) and rename it."""
        self._flush()
        if self._writer is None:
            return write_parquet(links_table(empty), self.path)
        self._writer.close()
        self.tmp.replace(self.path)
        return self.path

    def abort(self) -> None:
        """Drop the temporary file (the run failed)."""
        if self._writer is not None:
            self._writer.close()
        self.tmp.unlink(missing_ok=True)


#: ``links="auto"``: the links table is written only up to this many expected rows (about 28 bytes
#: each in parquet: some 60 MB); longer or larger runs skip it unless asked for (``links="on"``)
AUTO_LINKS_MAX_ROWS = 2_000_000
LINKS_CHOICES = ("auto", "on", "off")


def expected_link_rows(cfg: ScenarioConfig, n_subframes: int) -> int:
    """Rows the links table of a run would have (one per transmission and receiver in range), from
    the memory model's pair count (:func:`cv2x_marl.sim.memory.estimate_memory_bytes`)."""
    on = cfg if cfg.metrics.record_links else apply_overrides(cfg, ["metrics.record_links=true"])
    return int(estimate_memory_bytes(on, n_subframes)["links_table"] // (2 * LINK_ROW_BYTES))


def simulate(
    cfg: ScenarioConfig,
    seed: int,
    n_subframes: int,
    out_dir: Path | None,
    progress: bool = True,
    overwrite: bool = False,
    links: str = "on",
) -> dict[str, Any]:
    """Reset, run and (when ``out_dir``) write ``links.parquet``, ``summary.json``, ``prr_vs_distance.png``.

    ``out_dir`` is a run folder (:class:`cv2x_marl.runs.RunFolder`): locked, refused when not
    empty unless ``overwrite``, removed again if the run fails.

    Args:
        links: the links table: ``on`` as ``metrics.record_links`` says, ``off`` never, ``auto`` (the
            CLI's default) as ``metrics.record_links`` says up to :data:`AUTO_LINKS_MAX_ROWS` expected
            rows, skipped above (the summary's ``links_table`` says so and why). Without ``out_dir``
            the table is never built (nowhere to write it), whatever ``links`` says.
    """
    if links not in LINKS_CHOICES:
        raise ValueError(f"links must be one of {', '.join(LINKS_CHOICES)}, got {links!r}")
    note: dict[str, Any] | None = None
    if (links == "off" or out_dir is None) and cfg.metrics.record_links:  # no folder: nowhere to write it
        cfg = apply_overrides(cfg, ["metrics.record_links=false"])
    elif links == "auto" and cfg.metrics.record_links and out_dir is not None:
        rows = expected_link_rows(cfg, n_subframes)
        if rows > AUTO_LINKS_MAX_ROWS:
            cfg = apply_overrides(cfg, ["metrics.record_links=false"])
            note = {
                "written": False,
                "expected_rows": rows,
                "why": f"more than {AUTO_LINKS_MAX_ROWS:,} expected rows; pass --links on to write it",
            }
    params = {"seed": seed, "n_subframes": n_subframes, "links": links}
    with run_folder(out_dir, "simulate", overwrite=overwrite, parameters=params):
        return _simulate(cfg, seed, n_subframes, out_dir, progress, links_note=note)


class SlotOccupancy:
    """``vehicles.population=open``: which vehicle held each simulator slot when, read after every
    reservation period (the moment vehicles enter and leave), as intervals of subframes.

    Rows ``(slot, vehicle_id, first_subframe, end_subframe)``: the vehicle held the slot for the
    subframes ``[first_subframe, end_subframe)`` of the measured run (subframe 0 is the first one
    measured); the links table's ``tx`` / ``rx`` are slots, so this table says whose links they are.
    """

    def __init__(self, sim: Simulator) -> None:
        self.sim = sim
        self.start = sim.subframe
        self.rows: list[tuple[int, str, int, int]] = []
        self._held: dict[int, tuple[str, int]] = {}
        self.present_counts: list[int] = []
        self._observe()

    def _observe(self) -> None:
        ids = self.sim.vehicle_ids or []
        now = self.sim.subframe - self.start
        for k, (vid, since) in list(self._held.items()):
            if ids[k] != vid:
                self.rows.append((k, vid, since, now))
                del self._held[k]
        for k, new in enumerate(ids):
            if new is not None and k not in self._held:
                self._held[k] = (new, now)
        self.present_counts.append(sum(v is not None for v in ids))

    def update(self, done: int) -> None:
        """The simulator's progress callback: read the slots at each period end."""
        if self.sim.subframe % self.sim.rri == 0:
            self._observe()

    def table(self) -> pa.Table:
        """The intervals, those still open closed at the end of the run."""
        end = self.sim.subframe - self.start
        rows = sorted(self.rows + [(k, vid, since, end) for k, (vid, since) in self._held.items()])
        slot, vid, first, last = zip(*rows, strict=True) if rows else ((), (), (), ())
        return pa.table(
            {
                "slot": pa.array(slot, pa.int64()),
                "vehicle_id": pa.array(vid, pa.string()),
                "first_subframe": pa.array(first, pa.int64()),
                "end_subframe": pa.array(last, pa.int64()),
            }
        )


def _simulate(
    cfg: ScenarioConfig,
    seed: int,
    n_subframes: int,
    out_dir: Path | None,
    progress: bool,
    links_note: dict[str, Any] | None = None,
) -> dict[str, Any]:
    from tqdm import tqdm

    t0 = time.perf_counter()
    sim = Simulator(cfg)
    sim.reset(seed)
    # the links table streams into links.parquet (bounded memory); without an output it is not kept
    writer = LinksWriter(Path(out_dir) / "links.parquet") if out_dir is not None else None
    sink = writer if writer is not None else (lambda chunk: None)
    slots = SlotOccupancy(sim) if sim.present is not None else None
    try:
        with tqdm(total=n_subframes, unit="sf", desc="simulate", file=sys.stderr, disable=not progress) as bar:

            def tick(done: int) -> None:
                bar.update(done)
                if slots is not None:
                    slots.update(done)

            result = sim.run(n_subframes, progress=tick, links_sink=sink)
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    summary: dict[str, Any] = result.metrics.summary()
    summary.update(
        {
            "seed": seed,
            "n_subframes": n_subframes,
            "n_vehicles": cfg.n_vehicles,
            "n_slots": sim.n,
            "n_reselections": sim.n_reselections,
            "runtime_s": result.runtime_s,
            "total_runtime_s": time.perf_counter() - t0,
            "prr_at_m": {str(d): result.metrics.prr_at(d) for d in (50, 100, 200, 300)},
            "versions": {
                "cv2x_marl": cv2x_marl.__version__,
                "numpy": np.__version__,
                "python": platform.python_version(),
            },
            "config": to_dict(cfg),
        }
    )
    if links_note is not None:  # links="auto" skipped the table
        summary["links_table"] = links_note
    occ: pa.Table | None = None
    if slots is not None:  # vehicles.population=open
        occ = slots.table()
        counts = np.array(slots.present_counts)
        first, end = occ.column("first_subframe").to_numpy(), occ.column("end_subframe").to_numpy()
        summary["population"] = {  # over the measured run, read at every period end
            "present_mean": float(counts.mean()),
            "present_min": int(counts.min()),
            "present_max": int(counts.max()),
            "n_entered": int(np.sum(first > 0)),
            "n_left": int(np.sum(end < n_subframes)),
            "n_vehicles_seen": len(set(occ.column("vehicle_id").to_pylist())),
        }
    if out_dir is not None:
        out_dir = Path(out_dir)
        if occ is not None:
            write_parquet(occ, out_dir / "slots.parquet")
        if cfg.metrics.record_links and writer is not None:
            writer.close({c: np.empty(0) for c in LINK_COLUMNS})
        write_json(out_dir / "summary.json", summary)
        from cv2x_marl.plotting import plot_prr_vs_distance

        plot_prr_vs_distance(summary, out_dir / "prr_vs_distance.png")
    return summary
