"""The base install: both envs without torch or stable-baselines3, errors that name the extra,
ids that resolve in a fresh process."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from cv2x_marl.extras import MissingExtraError, missing_extra, require

# a fresh interpreter in which torch and stable-baselines3 cannot be imported (as after a base install)
BLOCK = textwrap.dedent(
    """
    import sys
    class _Block:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("torch", "stable_baselines3", "tensorboard"):
                raise ImportError(f"No module named {name!r} (blocked by the test)")
            return None
    sys.meta_path.insert(0, _Block())
    """
)


def _run(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", BLOCK + textwrap.dedent(code)], capture_output=True, text=True, timeout=300
    )


def test_both_envs_work_without_the_train_extra() -> None:
    proc = _run(
        """
        import numpy as np, gymnasium, pettingzoo, cv2x_marl
        kw = {"overrides": ["sim.warmup_subframes=200"], "max_cycles": 3}
        par = pettingzoo.make("parallel", "cv2x/Mobility-v2", **kw)
        obs, _ = par.reset(seed=0)
        par.step({a: np.zeros(2, np.float32) for a in par.agents})
        g = gymnasium.make("cv2x/SingleMover-v2", **kw)
        g.reset(seed=0)
        g.step(np.zeros(2, np.float32))
        assert "torch" not in sys.modules and "stable_baselines3" not in sys.modules
        try:
            import cv2x_marl.rl.sb3_vec_env
        except ImportError as exc:
            print("ERR", exc)
        from cv2x_marl.cli import main
        sys.exit(main(["evaluate", "--policy", "ppo:agents/models/single_seed0/model.zip", "--episodes", "1",
                       "--quiet", "--max-cycles", "3"]))
        """
    )
    assert "ERR the SB3 adapter (cv2x_marl.rl) needs stable_baselines3" in proc.stdout, proc.stderr
    assert "pip install 'cv2x_marl[train]'" in proc.stdout
    # the CLI reports the missing extra as an error (exit 2), not a traceback
    assert proc.returncode == 2, proc.stderr
    assert "cv2x_marl[train]" in proc.stderr and "Traceback" not in proc.stderr


def test_gymnasium_ids_resolve_in_a_fresh_process_without_importing_the_package() -> None:
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            "import gymnasium; e = gymnasium.make('cv2x_marl:cv2x/SingleMover-v2', max_cycles=2, "
            "overrides=['sim.warmup_subframes=200']); print(e.reset(seed=1)[0].shape)",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "(174,)"


def test_require_names_the_extra() -> None:
    with pytest.raises(MissingExtraError, match=r"cv2x_marl\[train\]"):
        require("torch_that_does_not_exist", "a test")
    assert "pip install 'cv2x_marl[train]'" in str(missing_extra("torch", "training"))
    assert require("numpy", "a test").__name__ == "numpy"


def test_cli_start_imports_nothing_heavy() -> None:
    """``cv2x-marl --help`` (and argument errors) load no fitting, learning or SUMO library: the
    commands import what they need when they run (issue 13: a CLI that starts in a fraction of a
    second instead of 3.6 s)."""
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys, cv2x_marl.cli as c\n"
            "p = c.build_parser()\n"
            "heavy = ('sklearn', 'scipy', 'torch', 'stable_baselines3', 'ray', 'libsumo', 'matplotlib', 'pandas',\n"
            "         'gymnasium', 'pettingzoo', 'numpy')\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & set(heavy)))",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


@pytest.mark.parametrize(
    "first",
    ["", "import gymnasium\n", "import pettingzoo\n", "import gymnasium, pettingzoo\n"],
    ids=["cv2x_marl-first", "gymnasium-first", "pettingzoo-first", "both-first"],
)
def test_ids_registered_whichever_package_is_imported_first(first: str) -> None:
    """``import cv2x_marl`` imports neither Gymnasium nor PettingZoo (the CLI starts without them), yet
    the ids are there as soon as either is imported, before or after the package."""
    code = (
        first
        + "import sys, cv2x_marl\n"
        + "print(sorted(m for m in ('gymnasium', 'pettingzoo') if m in sys.modules))\n"
        + "import gymnasium, pettingzoo\n"
        + "print(all(f'cv2x/SingleMover-{v}' in gymnasium.registry for v in ('v0', 'v1', 'v2')))\n"
        + "print(all(f'cv2x/Mobility-{v}' in r for v in ('v0', 'v1', 'v2')\n"
        + "          for r in (pettingzoo.parallel_registry, pettingzoo.aec_registry)))\n"
        + "env = gymnasium.make('cv2x/SingleMover-v2', max_cycles=3)\n"
        + "print(env.reset(seed=1)[0].shape)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    imported, gym_ok, pz_ok, shape = proc.stdout.split("\n")[:4]
    # PettingZoo imports Gymnasium, so importing it first imports both
    expected = {"": [], "import gymnasium\n": ["gymnasium"]}.get(first, ["gymnasium", "pettingzoo"])
    assert imported == str(expected)
    assert gym_ok == "True" and pz_ok == "True" and shape == "(174,)"
