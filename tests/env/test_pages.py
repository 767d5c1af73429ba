"""The generated env pages: one per registered id, current, every observation index described, snippets that run."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from cv2x_marl.env.observation import ObservationLayout
from cv2x_marl.env.observation_entries import entry_table
from cv2x_marl.env.pages import page_name, pages
from cv2x_marl.env.registry import ENV_IDS, make_parallel_env

DOCS = Path(__file__).resolve().parents[2] / "docs" / "envs"


def test_every_id_has_its_page_and_every_page_is_current() -> None:
    generated = pages()
    assert set(generated) == {"README.md", *(page_name(i) for i in ENV_IDS)}
    on_disk = {p.name for p in DOCS.glob("*.md")}
    assert on_disk == set(generated), "regenerate with: python -m cv2x_marl.env.pages docs/envs"
    stale = [name for name, text in generated.items() if (DOCS / name).read_text(encoding="utf-8") != text]
    assert stale == [], f"stale pages {stale}: regenerate with python -m cv2x_marl.env.pages docs/envs"


def _indices(layout: ObservationLayout) -> list[int]:
    out = []
    for e in entry_table(layout):
        out += list(range(e.first, e.last + 1, e.step))
    return sorted(out)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_the_observation_table_describes_every_index_once(env_id: str) -> None:
    layout = make_parallel_env(env_id).layout
    assert _indices(layout) == list(range(layout.size))


@pytest.mark.parametrize(
    ("version", "privileged", "drive"), [(1, True, False), (2, True, False), (0, False, True), (4, False, True)]
)
def test_the_table_follows_privileged_and_driving_layouts(version: int, privileged: bool, drive: bool) -> None:
    layout = ObservationLayout(5, 100.0, 400.0, 150.0, version=version, privileged=privileged, drive=drive)
    assert _indices(layout) == list(range(layout.size))
    names = [e.name for e in entry_table(layout)]
    assert ("true_p[k]" in names) == privileged
    assert ("speed" in names) == drive


def test_the_documented_indices_are_the_ones_the_env_writes() -> None:
    """Spot checks against a real observation: the own drift entries and the time left of SingleMover-v3."""
    env = make_parallel_env("cv2x/SingleMover-v3", max_cycles=4, overrides=["sim.warmup_subframes=200"])
    obs, _ = env.reset(seed=1)
    rows = {e.name: e for e in entry_table(env.layout)}
    o = obs["vehicle_0"]
    assert o[rows["time_left"].first] == pytest.approx(1.0)
    assert o[rows["elapsed"].first] == 0.0
    obs, *_ = env.step({a: [1.0, 0.0] for a in env.agents})
    o = obs["vehicle_0"]
    assert o[rows["time_left"].first] == pytest.approx(0.75)
    assert o[rows["elapsed"].first] == pytest.approx(0.25)
    # vehicle 0 moved 5 m along x (max_step_m 5, scale_m 100): both drift entries of the page say so
    drift = [e.first for e in entry_table(env.layout) if e.name == "drift_x"]
    assert len(drift) == 2 and all(o[i] == pytest.approx(0.05, rel=1e-5) for i in drift)


@pytest.mark.parametrize("env_id", ["cv2x/SingleMover-v3", "cv2x/Traffic-v1"])
def test_the_policy_snippet_of_a_page_runs_as_written(env_id: str) -> None:
    text = (DOCS / page_name(env_id)).read_text(encoding="utf-8")
    section = text.split("## Policies", 1)[1]
    code = re.findall(r"```python\n(.*?)```", section, flags=re.S)[0]
    scope: dict[str, object] = {}
    exec(compile(code, f"{page_name(env_id)} (Policies)", "exec"), scope)  # the page's own snippet
    env = scope["env"]
    assert env.t == 100  # type: ignore[attr-defined]  # the episode ran its 100 steps
