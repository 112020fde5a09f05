"""The generated configuration reference (docs/configuration.md) read back as rows, the config
class each key lives in, and BAD: a bad value or a misspelt key of each mapper part with the
name its one-line error must give (tried through the composition and through the command)."""

from __future__ import annotations

import dataclasses
import re

from slamkit.registry import default_registry
from slamkit.registry.schema import RunConfig, run_groups

from support.data import REPO

REFERENCE = REPO / "docs" / "configuration.md"
#: Top-level sections of keys that are not a role's (each the RunConfig field holding them).
TOP_SECTIONS = tuple(run_groups())


def reference_keys() -> list[tuple[str, str, str, str]]:
    """(section, key, type, default) of every row of docs/configuration.md; section is "" for the
    top level, "growth" / "eval" / ..., or "group=name" (`tracker=gicp`, `mapper/rasterizer=cpu`)."""
    rows, section = [], ""
    for line in REFERENCE.read_text().splitlines():
        heading = re.match(r"#+ `([\w/]+)(?:=(\w+|\.\.\.)|\.\*)`", line)
        if heading:
            section = f"{heading.group(1)}={heading.group(2)}" if heading.group(2) else heading.group(1)
            if heading.group(2) == "...":
                section = ""  # the role's heading before its plugins
        cells = [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line)[1:-1]]
        if len(cells) == 4 and re.fullmatch(r"`[\w.]+`", cells[0]):
            rows.append((section, cells[0].strip("`"), cells[1], cells[2].strip("`")))
    return rows


def config_class(section: str, key: str) -> type:
    """The dataclass that holds `key` of a section (a config nested in the section's: its class)."""
    if section in ("", *TOP_SECTIONS):
        return {"": RunConfig, **run_groups()}[section]
    group, name = section.split("=")
    cls = default_registry().get(group.split("/")[-1], name).config
    depth = len(group.split("/"))  # the key segments that name the section (mapper.rasterizer.)
    for field_name in key.split(".")[depth:-1]:  # e.g. mapper.admission.skip_covered
        cls = type(next(f for f in dataclasses.fields(cls) if f.name == field_name).default_factory())
    return cls


#: (the part chosen, the bad override, what its one-line error names)
BAD = [
    ("mapper/sampler=covisible", "mapper.sampler.top_k=-1", "mapper.sampler.top_k"),
    ("mapper/rasterizer=gsplat", "mapper.rasterizer.tile_size=0", "mapper.rasterizer.tile_size"),
    ("mapper/rasterizer=torch", "mapper.rasterizer.max_pairs_per_chunk=10", "mapper.rasterizer.max_pairs_per_chunk"),
    ("mapper/rasterizer=cpu", "mapper.rasterizer.num_threads=-2", "mapper.rasterizer.num_threads"),
    ("mapper/strategy=3dgs", "mapper.strategy.grad_threshold=0", "mapper.strategy.grad_threshold"),
    ("mapper/optimizer=adam", "mapper.optimizer.lr_means=-1", "mapper.optimizer.lr_means"),
    ("mapper/loss=l1_ssim_depth", "mapper.loss.weight_ssim=-0.2", "mapper.loss.weight_ssim"),
    ("mapper/strategy=gsicp", "mapper.strategy.prune_evry=100", "prune_evry"),
    ("mapper/sampler=covisible", "mapper.sampler.topk=3", "topk"),
    ("mapper/optimizer=visible_adam", "mapper.optimizer.only_visible=maybe", "mapper.optimizer.only_visible"),
]
