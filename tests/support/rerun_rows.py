"""What a rerun recording (.rrd) holds, read back with rerun's own reader: for the tests of
`viewer=rerun` through the command."""

from __future__ import annotations

from collections import Counter
from pathlib import Path


def rrd_rows(path: Path) -> tuple[Counter, dict[int, int]]:
    """Rows logged per entity (non-static), and the number of map points logged at each frame."""
    from rerun.chunk import RrdReader

    rows: Counter = Counter()
    map_sizes: dict[int, int] = {}
    for chunk in RrdReader(str(path)).stream().to_chunks():
        if chunk.is_static:
            rows[chunk.entity_path + " (static)"] += chunk.num_rows
            continue
        rows[chunk.entity_path] += chunk.num_rows
        if chunk.entity_path == "/world/map":
            batch = chunk.to_record_batch()
            frames = batch.column(batch.schema.names.index("frame")).to_pylist()
            positions = batch.column(batch.schema.names.index("GaussianSplats3D:centers")).to_pylist()
            map_sizes.update({f: len(p) for f, p in zip(frames, positions)})
    return rows, map_sizes
