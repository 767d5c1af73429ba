"""The ``cv2x-marl`` command line."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from cv2x_marl import interrupts, runs
from cv2x_marl.config import (
    PRESET_ALIASES,
    PRESETS,
    TRUTH_LOS,
    ConfigError,
    ScenarioConfig,
    apply_overrides,
    config_markdown,
    load_config_file,
    preset,
    show_value,
    to_dict,
)
from cv2x_marl.env.registry import ENV_IDS
from cv2x_marl.experiments.benchmark import add_arguments as _benchmark_arguments
from cv2x_marl.experiments.benchmark import run_from_args as _cmd_benchmark
from cv2x_marl.extras import MissingExtraError
from cv2x_marl.io import dumps_json
from cv2x_marl.rl.errors import TrainError

#: agent-steps of `cv2x-marl train` when neither --timesteps nor the config file says
DEFAULT_TIMESTEPS = 200_000
#: dataset readings: ``per-packet`` (the settings as given) or ``paper`` (the paper's Table 3 instances)
READINGS = ("per-packet", "paper")
#: the env ids `evaluate`, `train`, `sweep` and `baselines` accept, newest first (the registry imports
#: no env code, so `--help` stays fast)
ENV_CHOICES = ENV_IDS[::-1]
#: the `--preset` choices
PRESET_CHOICES = sorted([*PRESETS, *PRESET_ALIASES])


def _number_type(
    kind: type, low: float, low_open: bool, high: float | None = None, high_open: bool = True
) -> Callable[[str], Any]:
    """An argparse ``type`` that accepts finite ``kind`` values in the range and names the rule otherwise
    (the text shown cut to 60 characters; integers of any length are compared exactly)."""

    def fmt(x: float) -> str:
        return str(int(x)) if kind is int else f"{x:g}"

    lo = f"{'>' if low_open else '>='} {fmt(low)}"
    rule = f"{'an integer' if kind is int else 'a finite number'} {lo}"
    if high is not None:
        rule += f" and {'<' if high_open else '<='} {fmt(high)}"

    def parse(text: str) -> float | int:
        refusal = f"must be {rule}, got {show_value(text)}"
        try:
            value = kind(text)
        except ValueError:
            try:  # an integer written in scientific notation (--timesteps 1e5)
                as_float = float(text)
            except ValueError:
                raise argparse.ArgumentTypeError(refusal) from None
            if kind is not int or not as_float.is_integer():  # inf and NaN are not integers
                raise argparse.ArgumentTypeError(refusal) from None
            value = int(as_float)
        ok = (kind is int or math.isfinite(value)) and (value > low if low_open else value >= low)
        if high is not None:
            ok = ok and (value < high if high_open else value <= high)
        if not ok:
            raise argparse.ArgumentTypeError(refusal)
        return value

    return parse


OVERWRITE_HELP = (
    "replace a previous run in --out (kept until this run completes); without it a non-empty --out is refused"
)

POSITIVE_FLOAT = _number_type(float, 0.0, True)
FRACTION = _number_type(float, 0.0, True, 1.0, True)
COUNT = _number_type(int, 1, False)
#: ``evaluate``'s episodes without ``--episodes`` or ``--seeds``
EVALUATE_EPISODES = 144
#: the largest seed: seeds are 32-bit (numpy's legacy seeding, which stable-baselines3 calls, takes < 2**32)
MAX_SEED = 2**32 - 1
SEED = _number_type(int, 0, False, MAX_SEED, False)


def _print_json(data: object) -> None:
    sys.stdout.write(dumps_json(data) + "\n")


def _scenario(args: argparse.Namespace) -> ScenarioConfig:
    """``--preset`` (default paper), then the ``--config`` file (whose ``preset:`` line, if any, must
    name the same preset as a given ``--preset``), then the ``--set`` overrides."""
    cfg = preset(args.preset or "paper")
    if args.config:
        cfg = load_config_file(args.config, cfg, given_preset=args.preset)
    return apply_overrides(cfg, args.set or [])


def _add_scenario_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--preset",
        default=None,
        choices=PRESET_CHOICES,
        help="base configuration (default: paper, or the --config file's preset: line; naming two "
        "different presets is refused)",
    )
    p.add_argument("--config", type=Path, help="YAML/JSON file of configuration sections applied over the preset")
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override one key, e.g. --set sps.n_subchannels=4 (repeatable)",
    )


def _cmd_simulate(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.simulate import simulate

    cfg = _scenario(args)
    n = args.subframes if args.subframes is not None else cfg.sim.n_subframes
    if n < 1:
        raise ConfigError(f"--subframes must be >= 1, got {n}")
    if n != cfg.sim.n_subframes:  # the memory check (and run.json's config) see the run's real length
        cfg = apply_overrides(cfg, [f"sim.n_subframes={n}"])
    summary = simulate(cfg, args.seed, n, args.out, progress=not args.quiet, overwrite=args.overwrite, links=args.links)
    if "links_table" in summary:
        note = summary["links_table"]
        print(f"links.parquet not written: {note['expected_rows']:,} rows expected; {note['why']}", file=sys.stderr)
    if args.json:
        _print_json(summary)
    else:
        pop = summary.get("population")
        vehicles = (
            f"{summary['n_vehicles']} vehicles"
            if pop is None
            else f"{pop['n_vehicles_seen']} vehicles ({pop['present_mean']:.1f} present on average)"
        )
        print(
            f"PRR mean {summary['prr_mean']:.4f} (expected {summary['prr_mean_expected']:.4f}) over "
            f"{vehicles}, {summary['n_transmissions']} transmissions, {summary['runtime_s']:.3f} s"
        )
        print("PRR at " + ", ".join(f"{d} m: {p:.3f}" for d, p in summary["prr_at_m"].items()))
        print("loss causes: " + ", ".join(f"{k} {v:.1%}" for k, v in summary["loss_cause_shares"].items()))
        if args.out:
            for name in ("links.parquet", "slots.parquet", "summary.json", "prr_vs_distance.png"):
                if (args.out / name).exists():
                    print(f"wrote {args.out / name}")
    return 0


def _cmd_dataset(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.dataset import build_dataset

    cfg = _scenario(args)
    if args.subframes is not None:
        cfg = apply_overrides(cfg, [f"sim.n_subframes={args.subframes}"])
    window_ms = args.aggregate_window_ms
    if args.reading == "paper":
        if window_ms:
            raise ConfigError("--reading paper aggregates over the whole run; drop --aggregate-window-ms")
        if cfg.metrics.nsv_scope != "concurrent" and any(
            s.split("=", 1)[0].strip() == "metrics.nsv_scope" for s in args.set or []
        ):
            raise ConfigError("--reading paper sets metrics.nsv_scope=concurrent; drop --set metrics.nsv_scope")
        cfg = apply_overrides(cfg, ["metrics.nsv_scope=concurrent"])
        from cv2x_marl.experiments.dataset import WHOLE_RUN

        window_ms = WHOLE_RUN  # one window per run, however long the warm-up (sim.warmup_mode)
    manifest = build_dataset(
        cfg,
        args.runs,
        args.seed,
        args.out,
        window_ms,
        progress=not args.quiet,
        overwrite=args.overwrite,
        ray=args.ray or args.address is not None,
        address=args.address,
    )
    if args.json:
        _print_json({k: v for k, v in manifest.items() if k != "config"})
    else:
        print(f"{manifest['rows']} samples from {args.runs} runs in {manifest['runtime_s']:.2f} s")
        print("rows per NSV: " + ", ".join(f"{k}: {v}" for k, v in manifest["rows_per_nsv"].items()))
        print(f"wrote {args.out / 'samples.parquet'} and {args.out / 'manifest.json'}")
    return 0


def _cmd_fit(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.dataset import run_fit

    result = run_fit(
        args.data,
        args.out,
        kind=args.model,
        target=args.target,
        nsv_cap=args.nsv_cap,
        test_fraction=args.test_fraction,
        seed=args.seed,
        min_samples=args.min_samples,
        compare=args.compare,
        figures=not args.no_figures,
        overwrite=args.overwrite,
    )
    if args.json:
        _print_json(result)
    else:
        print(f"{'NSV':>4} {'alpha':>7} {'beta':>7} {'gamma':>7} {'R2':>6} {'R2test':>7} {'instances':>9}")
        for r in result["per_nsv"]:
            fb = f"  (from NSV {r['fallback_from']})" if r.get("fallback_from") is not None else ""
            print(
                f"{r['nsv']:>4} {r['alpha']:7.3f} {r['beta']:7.3f} {r['gamma']:7.3f} {r['r2']:6.3f} "
                f"{r['r2_test']:7.3f} {r['instances']:9d}{fb}"
            )
        for k, o in result.get("comparison", {}).items():
            print(f"held out, {k}: R2 {o['r2']:.3f}, Brier {o['brier']:.4f}, log-loss {o['log_loss']:.4f}")
        print(f"wrote {result['model']}, table2.md, table3.md and figures in {args.out}")
    return 0


def _cmd_gbmu(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.gbmu_study import check_methods, run_study
    from cv2x_marl.regression.model import load_model, resolve_model

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    check_methods(methods, args.methods)  # before the model is read
    cfg = _scenario(args)
    model = load_model(resolve_model(str(args.model)))
    summary = run_study(
        args.case,
        cfg,
        model,
        args.out,
        seed=args.seed,
        realizations=args.realizations,
        iterations=args.iterations,
        delta=args.step,
        th_pos_m=args.th_pos,
        truth_los=args.truth_los,
        methods=methods,
        progress=not args.quiet,
        overwrite=args.overwrite,
        judge=args.judge,
    )
    if args.json:
        _print_json({k: v for k, v in summary.items() if k != "config"})
    else:
        print(f"case {args.case}, {summary['n_realizations']} realisation(s), model {model.kind}, judge {args.judge}")
        for name, m in summary["methods"].items():
            share = m.get("share_of_optimum")
            share_txt = "" if share is None else f", {share:.1%} of the optimum's gain"
            print(
                f"{name:>7}: effectiveness {m['effectiveness']:.1%}, utility gain {m['mean_utility_gain']:+.1%}, "
                f"PRR gain {m['mean_prr_gain']:+.1%}, PRR drops {m['n_prr_drop']}, moved {m['mean_moved_m']:.1f} m"
                + share_txt
            )
        if args.out:
            print(f"wrote {args.out}/summary.json, realizations.csv and figures")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments import evaluate as ev
    from cv2x_marl.regression.model import resolve_model

    env_kwargs = {"preset": args.preset, "overrides": args.set or [], "max_cycles": args.max_cycles}
    env_kwargs["max_step_m"] = args.max_step
    if args.replan_every is not None:
        env_kwargs["replan_every"] = args.replan_every
    env_kwargs.update(ev.parse_env_options(args.env_option or [], ev.EVALUATE_FLAGS))
    policies = ev.expand_policies(args.policy or ["gbmu"])
    seeds = ev.cli_seeds(args.seeds, args.episodes, args.seed, args.env, policies)
    summary = ev.evaluate(
        args.env,
        policies if len(policies) > 1 else policies[0],
        EVALUATE_EPISODES if args.episodes is None else args.episodes,
        0 if args.seed is None else args.seed,
        args.out,
        env_kwargs,
        model_path=resolve_model(str(args.model)),
        delta=args.delta,
        progress=not args.quiet,
        vs_optimum=args.vs_optimum,
        overwrite=args.overwrite,
        seeds=seeds,
    )
    if args.json:
        _print_json(summary)
    else:
        print(ev.format_summary(summary, ", ".join(args.policy or ["gbmu"])))
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from cv2x_marl.rl.mappo_config import config_algo
    from cv2x_marl.rl.train import load_train_config, run_settings, train

    if config_algo(args.config, args.algo) == "mappo":  # docs/rl.md, "MAPPO"
        from cv2x_marl.rl.mappo import cli_train

        return cli_train(args, DEFAULT_TIMESTEPS, _print_json)
    cfg = load_train_config(args.config, env_id=args.env, copies=args.copies)
    from_file = run_settings(args.config)  # a run folder's train_config.json names its seed and length
    timesteps = args.timesteps if args.timesteps is not None else from_file.get("timesteps", DEFAULT_TIMESTEPS)
    seed = args.seed if args.seed is not None else from_file.get("seed", 0)
    quiet, resume, overwrite = args.quiet, args.resume, args.overwrite
    record = train(cfg, timesteps, seed, args.out, resume=resume, progress=not quiet, overwrite=overwrite)
    if args.json:
        _print_json(record)
    else:
        fe = record["final_eval"]
        print(
            f"trained {record['timesteps']} steps in {record['wall_s']:.1f} s ({record['steps_per_s']:.0f} steps/s); "
            f"eval: utility gain {fe['mean_utility_gain']:+.1%}, effectiveness {fe['effectiveness']:.1%}, "
            f"PRR gain {fe['mean_prr_gain']:+.1%}"
        )
        print(f"wrote {args.out / 'model.zip'}, record.json, eval.csv, checkpoints/, tb/")
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from cv2x_marl.rl.sweep import parse_grid, run_sweep
    from cv2x_marl.rl.train import load_train_config

    cfg = load_train_config(args.config, env_id=args.env)
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        raise TrainError(f"--seeds expects integers separated by commas, got {args.seeds!r}") from None
    if any(s < 0 for s in seeds):
        raise TrainError(f"--seeds must be integers >= 0, got {args.seeds!r}")
    result = run_sweep(
        cfg,
        seeds,
        parse_grid(args.grid or []),
        args.timesteps,
        args.out,
        address=args.address,
        eval_episodes=args.eval_episodes,
        eval_seed=args.eval_seed,
        vs_optimum=args.vs_optimum,
        overwrite=args.overwrite,
        progress=not args.quiet,
    )
    if args.json:
        _print_json(result)
    else:
        for p in result["points"]:
            sd = "" if p["std_utility_gain"] is None else f" +- {p['std_utility_gain']:.1%}"
            gain = "failed" if p["mean_utility_gain"] is None else f"{p['mean_utility_gain']:+.1%}{sd}"
            print(f"{p['label']}: held-out utility gain {gain} over {p['trials']} seed(s)")
        print(f"wrote {args.out / 'trials.csv'}, results.json, sweep.png and trials/ ({result['wall_s']:.0f} s)")
    return 0


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.reproduce import NO_MODELS, reproduce

    report = reproduce(
        args.out,
        quick=args.quick,
        seed=args.seed,
        models_dir=None if str(args.models) == NO_MODELS else args.models,
        progress=not args.quiet,
        overwrite=args.overwrite,
    )
    print(f"wrote {args.out / 'REPORT.md'} and report.json ({report['runtime_s']:.0f} s)")
    return 0


def _cmd_baselines(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.baselines import run_baselines

    result = run_baselines(args.dir, args.episodes, args.seed, args.env, progress=not args.quiet)
    if args.json:
        _print_json(result)
    else:
        for r in result["rows"]:
            share = "" if r["share_of_optimum"] is None else f", {r['share_of_optimum']:.0%} of the optimum"
            print(f"{r['baseline']:10s} {r['env']}: utility gain {r['mean_utility_gain']:+.1%}{share}")
        print(f"wrote {args.dir / 'results.json'} and {args.dir / 'results.md'}")
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from cv2x_marl.validation.compare import assumption_sets, run_grid, run_validation

    params = {k: v for k, v in vars(args).items() if k not in ("func", "out", "overwrite", "command")}
    sets = [*assumption_sets(args.assumptions), *(args.set or [])]  # --set last: it overrides
    run = dict(n_subframes=args.subframes, seeds=args.seeds, sets=sets, workers=args.workers)
    with runs.run_folder(args.out, "validate", overwrite=args.overwrite, parameters=params):
        if args.study:
            run_grid(args.out, densities=args.densities, **run)
        else:
            run_validation(args.out, args.densities, args.packets_per_s, args.tx_power_dbm, args.subchannels, **run)
    return 0


def _cmd_sumo_export(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.sumo_export import export_scenario, export_seconds

    cfg = _scenario(args)
    export_seconds(cfg, args.seconds)  # the trace's size, refused before the folder is touched
    params = {"seed": args.seed, "seconds": args.seconds, "parquet": args.parquet}
    with runs.run_folder(args.out, "sumo export", overwrite=args.overwrite, parameters=params):
        summary = export_scenario(cfg, args.seed, args.out, args.seconds, args.parquet)
    if args.json:
        _print_json(summary)
    else:
        print(
            f"SUMO {summary['sumo_version']} scenario (seed {summary['seed']}, SUMO seed {summary['sumo_seed']}): "
            f"{summary['n_vehicles']} vehicles over {summary['n_timesteps']} steps of {summary['step_s']:g} s"
        )
        for name in summary["files"]:
            print(f"wrote {args.out / name}")
    return 0


def _cmd_config(args: argparse.Namespace) -> int:
    if args.markdown:
        sys.stdout.write(config_markdown())
    else:
        _print_json(to_dict(_scenario(args)))
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (also used by the docs)."""
    parser = argparse.ArgumentParser(prog="cv2x-marl", description="Controlled mobility in C-V2X Mode 4 networks")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="run the stage-1 network simulator")
    _add_scenario_args(p)
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--subframes", type=COUNT, help="subframes to simulate (default: sim.n_subframes)")
    p.add_argument("--out", type=Path, help="output folder for links.parquet, summary.json, prr_vs_distance.png")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument(
        "--links",
        choices=("auto", "on", "off"),
        default="auto",
        help="links.parquet: auto (default) writes it up to 2,000,000 expected rows (about 60 MB) and "
        "skips it above with a note; on: always (as metrics.record_links says); off: never",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser("dataset", help="stage-1 dataset: K independent runs of link samples")
    _add_scenario_args(p)
    p.add_argument("--runs", type=COUNT, default=10, help="independent runs (seeds derived from --seed)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--subframes", type=COUNT, help="subframes per run (default: sim.n_subframes)")
    p.add_argument(
        "--aggregate-window-ms",
        type=SEED,
        default=0,
        help="aggregate per (run, link, window, NSV) into an empirical reception rate (0: per transmission)",
    )
    p.add_argument(
        "--reading",
        choices=list(READINGS),
        default="per-packet",
        help="per-packet: one sample per transmission and co-channel NSV (the settings as given); paper: the "
        "paper's Table 3 reading, NSV over every concurrent transmitter (metrics.nsv_scope=concurrent) and one "
        "instance per (run, link, NSV) over the whole run (docs/model.md)",
    )
    p.add_argument("--out", type=Path, required=True, help="dataset folder")
    p.add_argument("--ray", action="store_true", help="run the runs as Ray tasks (a local Ray; the [ray] extra)")
    p.add_argument("--address", help="with --ray: the Ray cluster to use (auto, ray://HOST:10001)")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--json", action="store_true", help="print the manifest as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_dataset)

    p = sub.add_parser("fit", help="stage-2 fit of the two-distance model per NSV (eq. 15)")
    p.add_argument("--data", type=Path, required=True, help="dataset folder (from `cv2x-marl dataset`)")
    p.add_argument("--out", type=Path, required=True, help="fit folder: model.json, table2.md, table3.md, figures")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--model", default="linear", choices=["linear", "logistic"], help="model family")
    p.add_argument(
        "--target",
        default=None,
        choices=["p_success", "outcome", "rate"],
        help="what eq. 15 fits (default: rate for an aggregated dataset, e.g. --reading paper; else p_success)",
    )
    p.add_argument("--nsv-cap", type=COUNT, default=6, help="NSV values above are pooled into the cap")
    p.add_argument("--test-fraction", type=FRACTION, default=0.2, help="share of runs held out")
    p.add_argument("--min-samples", type=COUNT, default=30, help="below this an NSV borrows a neighbour's fit")
    p.add_argument("--seed", type=SEED, default=0, help="seed of the held-out split")
    p.add_argument("--compare", action="store_true", help="also fit the other family and compare on held-out data")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--json", action="store_true", help="print per-NSV coefficients and statistics as JSON")
    p.set_defaults(func=_cmd_fit)

    p = sub.add_parser("gbmu", help="GBMU mobility studies (Fig. 5-10) with greedy and oracle references")
    _add_scenario_args(p)
    p.add_argument("--case", default="realizations", choices=["seven-node", "snapshot", "realizations"])
    p.add_argument("--realizations", type=COUNT, default=144, help="snapshots in the realizations case")
    p.add_argument("--iterations", type=COUNT, default=10_000, help="iteration cap")
    p.add_argument("--step", type=POSITIVE_FLOAT, default=1.0, help="step size delta")
    p.add_argument("--th-pos", type=POSITIVE_FLOAT, default=1e-4, help="stop when a move is shorter than this (m)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument(
        "--model",
        type=Path,
        default=Path("paper-table2"),
        help="fit folder or model.json (from `cv2x-marl fit`), paper-table2 (default), or a shipped model: "
        "linear-fit, logistic-fit",
    )
    p.add_argument(
        "--methods",
        default="gbmu,greedy,oracle,planner,optimum",
        help="comma-separated: gbmu, greedy, oracle, planner (the steering model's best reachable position), "
        "optimum (the best reachable position under the judge); variants beyond the paper: gbmu-logistic, "
        "planner-logistic (the shipped logistic-fit model), gbmu-schedule (Armijo backtracking step), "
        "gbmu-logistic-schedule",
    )
    p.add_argument(
        "--truth-los",
        default="snapshot",
        choices=TRUTH_LOS,
        help="LOS state of the mover's links in the ground truth",
    )
    p.add_argument(
        "--judge",
        default="simulator",
        choices=["simulator", "model"],
        help="who scores utility and PRR: the link model (default) or the steering regression model",
    )
    p.add_argument("--out", type=Path, help="output folder")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_gbmu)

    p = sub.add_parser("evaluate", help="evaluate a mover policy on the env (same episodes for the same seed)")
    p.add_argument(
        "--env",
        default=None,
        choices=ENV_CHOICES,
        help="default: the env a ppo:PATH model was trained on, else cv2x/SingleMover-v2",
    )
    p.add_argument(
        "--policy",
        action="append",
        help="static | random | gbmu | greedy | oracle | planner | sensing | optimum | ppo:PATH | baselines/NAME.yaml "
        "(default gbmu); repeated, or a ppo:PATTERN glob: the training runs of one method, pooled",
    )
    p.add_argument(
        "--seeds",
        help="episode seeds: integers separated by commas, or heldout | train (the --env task's lists, "
        "docs/benchmark.md); adds IQM and 95%% bootstrap CIs (default: --episodes from --seed)",
    )
    p.add_argument("--env-option", action="append", metavar="KEY=VALUE", help="env argument, YAML value (repeatable)")
    p.add_argument("--vs-optimum", action="store_true", help="also the optimum on every episode: share_of_optimum")
    p.add_argument(
        "--episodes",
        type=COUNT,
        default=None,
        help=f"episodes (default {EVALUATE_EPISODES}); with --seeds, the first N of them; x movers at most "
        "1,000,000 (rows kept in memory)",
    )
    p.add_argument(
        "--seed", type=SEED, default=None, help="episode k resets with the k-th seed derived from it (default 0)"
    )
    p.add_argument("--preset", default="paper", choices=PRESET_CHOICES)
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="scenario override (repeatable)")
    p.add_argument(
        "--max-cycles", type=COUNT, default=100, help="steps per episode (the env's max_cycles, at most 10,000)"
    )
    p.add_argument(
        "--max-step",
        type=POSITIVE_FLOAT,
        default=5.0,
        help="offset of a full action (m; the env's max_step_m): at most the scene's diagonal, and -v1/-v2 envs "
        "refuse a reachable square (2 x max-cycles x max-step wide) whose 20 m plan grid exceeds 4,000,000 points",
    )
    p.add_argument(
        "--replan-every",
        type=COUNT,
        default=None,
        help="-v2 envs: recompute the sensing plan every N steps (default: a ppo:PATH model's setting, else once)",
    )
    p.add_argument(
        "--model",
        type=Path,
        default=Path("paper-table2"),
        help="two-distance model for gbmu/greedy/planner: a fit folder, a model.json, paper-table2 or a shipped "
        "model (linear-fit, logistic-fit)",
    )
    p.add_argument("--delta", type=POSITIVE_FLOAT, default=100.0, help="GBMU/greedy/oracle step size per env step")
    p.add_argument("--out", type=Path, help="output folder (episodes.csv, summary.json)")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--json", action="store_true")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("benchmark", help="every method of every task on its held-out episodes: table and figure")
    _benchmark_arguments(p, COUNT, OVERWRITE_HELP)
    p.set_defaults(func=_cmd_benchmark)

    p = sub.add_parser("train", help="train PPO movers (SB3, parameter sharing) or MAPPO (TorchRL, algo: mappo)")
    p.add_argument("--env", default=None, choices=ENV_CHOICES)
    p.add_argument("--algo", default=None, help="ppo | mappo (default: the --config file's algo, else ppo)")
    p.add_argument(
        "--timesteps",
        type=COUNT,
        default=None,
        help=f"total agent-steps (default: the --config file's timesteps, else {DEFAULT_TIMESTEPS:,})",
    )
    p.add_argument("--seed", type=SEED, default=None, help="training seed (default: the --config file's, else 0)")
    p.add_argument("--copies", type=COUNT, default=None, help="env copies (each mover of each copy is a sub-env)")
    p.add_argument("--config", type=Path, help="YAML/JSON: env_id, copies, env, ppo, checkpoint_every, eval_*")
    p.add_argument("--out", type=Path, required=True, help="run folder")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument(
        "--resume", action="store_true", help="continue the run in --out from its newest checkpoint (to --timesteps)"
    )
    p.add_argument("--json", action="store_true")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("sweep", help="PPO training sweep over seeds and a grid, as Ray Tune trials")
    p.add_argument("--config", type=Path, help="training config (as for train) the grid modifies")
    p.add_argument("--env", default=None, choices=ENV_CHOICES, help="env id (default: the config's)")
    p.add_argument("--seeds", default="0", help="training seeds, comma-separated (default: 0)")
    p.add_argument(
        "--grid",
        action="append",
        metavar="KEY=V1,V2",
        help="a training-config key and its values, e.g. ppo.learning_rate=1e-4,3e-4 or env.replan_every=25,50 "
        "(repeatable: the trials are seeds x every combination)",
    )
    p.add_argument("--timesteps", type=COUNT, default=50_000, help="agent-steps per trial")
    p.add_argument("--eval-episodes", type=COUNT, default=48, help="held-out episodes per trial")
    p.add_argument("--eval-seed", type=SEED, default=2026, help="seed of the held-out episodes")
    p.add_argument("--vs-optimum", action="store_true", help="also report each trial's share of the optimum")
    p.add_argument("--address", help="Ray cluster address (auto, ray://HOST:10001); default: a local Ray")
    p.add_argument("--out", type=Path, required=True, help="sweep folder")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--json", action="store_true", help='print {"trials": [...], "points": [...]} as JSON')
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_sweep)

    p = sub.add_parser("reproduce", help="dataset, fit, GBMU study, movers vs baselines, REPORT.md")
    p.add_argument("--out", type=Path, default=Path("results"))
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--quick", action="store_true", help="smaller settings: about four minutes on 2 cores")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument(
        "--models",
        type=Path,
        default=Path("agents/models"),
        help="folder of the PPO models, single_seed<N>/model.zip and multi_seed<N>/model.zip (checked before "
        "anything runs); none: no PPO rows",
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_reproduce)

    p = sub.add_parser("baselines", help="every baseline file of a folder on the same held-out episodes")
    p.add_argument("--dir", type=Path, default=Path("baselines"), help="folder of baseline files (*.yaml)")
    p.add_argument("--episodes", type=COUNT, default=144)
    p.add_argument("--seed", type=SEED, default=2026)
    p.add_argument("--env", default=None, choices=ENV_CHOICES, help="default: each file's env_id")
    p.add_argument("--json", action="store_true")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_baselines)

    p = sub.add_parser("sumo", help="SUMO mobility scenarios (the 'sumo' extra; docs/mobility.md)")
    sumo_sub = p.add_subparsers(dest="sumo_command", required=True)
    p = sumo_sub.add_parser(
        "export", help="write the generated SUMO scenario of a preset and seed (net, routes, .sumocfg, FCD trace)"
    )
    _add_scenario_args(p)
    p.add_argument(
        "--seed",
        type=SEED,
        default=0,
        help="run seed (with a preset of vehicles.mobility=sumo, e.g. sumo-grid: the scenario `simulate --seed` runs)",
    )
    p.add_argument(
        "--seconds",
        type=POSITIVE_FLOAT,
        default=None,
        help="SUMO seconds of FCD trace (default: sim.warmup_subframes + sim.n_subframes, plus 60 s); at most "
        "what keeps the trace within 10,000,000 rows (vehicles x SUMO steps; 47,619 s for 21 vehicles at 0.1 s)",
    )
    p.add_argument("--parquet", action="store_true", help="also write the trace as fcd.parquet")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=_cmd_sumo_export)

    p = sub.add_parser(
        "validate",
        help="PDR(d) and loss causes of the highway simulator against the analytical Mode 4 model of "
        "Gonzalez-Martin et al. (IEEE TVT 2019; docs/validation.md)",
    )
    p.add_argument(
        "--out", type=Path, required=True, help="output folder: validation.json, CSVs, one figure per density"
    )
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--densities", type=POSITIVE_FLOAT, nargs="+", default=[0.1, 0.2, 0.3], help="veh/m")
    p.add_argument("--packets-per-s", type=POSITIVE_FLOAT, default=10.0, help="packets per second per vehicle")
    p.add_argument("--tx-power-dbm", type=float, default=20.0, help="transmit power (dBm)")
    p.add_argument("--subchannels", type=int, default=4, choices=(2, 4), help="sub-channels per subframe")
    p.add_argument("--subframes", type=COUNT, default=5000, help="measured subframes per seed")
    p.add_argument("--seeds", type=SEED, nargs="+", default=[1, 2], help="simulator seeds (pooled)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a simulator key (repeatable)")
    p.add_argument("--study", action="store_true", help="every configuration of the study (docs/validation.md)")
    p.add_argument("--workers", type=COUNT, default=1, help="simulator runs in this many processes")
    assume = "model: the simulator under the analytical model's stated assumptions, before --set (docs/validation.md)"
    p.add_argument("--assumptions", choices=("simulator", "model"), default="simulator", help=assume)
    p.set_defaults(func=_cmd_validate)

    p = sub.add_parser("config", help="print the resolved configuration, or the key reference")
    _add_scenario_args(p)
    p.add_argument("--markdown", action="store_true", help="print docs/config.md (every key, unit, default, range)")
    p.set_defaults(func=_cmd_config)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cv2x-marl`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    runs.INVOCATION = ["cv2x-marl", *(sys.argv[1:] if argv is None else argv)]
    runs.INPUTS = _inputs(args)
    previous = interrupts.install_safe_handlers()
    try:
        return int(args.func(args))
    except ConfigError as exc:
        print(f"cv2x-marl: configuration error: {exc}{_notes(exc)}", file=sys.stderr)
        return 2
    except (ValueError, MissingExtraError) as exc:  # ConfigError, DatasetError, FitError, ModelError, TrainError, ...
        print(f"cv2x-marl: error: {exc}{_notes(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a folder that vanished: the run folder was rolled back
        where = f" ({exc.filename})" if exc.filename else ""
        print(f"cv2x-marl: file system error{where}: {exc.strerror or exc}{_notes(exc)}", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, SystemError) as exc:
        # Ctrl-C or SIGTERM; inside a numba kernel the interrupt surfaces as a SystemError caused by it
        if not runs.is_interrupt(exc):
            raise
        detail = f": {exc}" if isinstance(exc, KeyboardInterrupt) and str(exc) else ""
        print(f"\ncv2x-marl: interrupted{detail}{_notes(exc)}", file=sys.stderr)
        return 130
    finally:
        runs.INVOCATION = None
        runs.INPUTS = []
        interrupts.restore_handlers(previous)


def _notes(exc: BaseException) -> str:
    """What happened to the output folder (the notes :class:`cv2x_marl.runs.RunFolder` attached), as ``; ...``."""
    return "".join(f"; {n}" for n in runs.notes(exc))


def _inputs(args: argparse.Namespace) -> list[Path]:
    """The files and folders a command reads (``--config``, ``--data``, ``--model``, ``--models``, the
    file of ``--policy``): its ``--out`` may not be, contain or lie inside one of them."""
    found: list[Path] = []
    for name in ("config", "data", "model", "models"):
        value = getattr(args, name, None)
        if isinstance(value, Path):
            found.append(value)
    policy = getattr(args, "policy", None)
    for spec in [policy] if isinstance(policy, str) else policy or []:
        if spec.startswith("ppo:"):
            found.append(Path(spec[4:]))
        elif spec.endswith((".yaml", ".yml", ".json")):
            found.append(Path(spec))
    return found


def console() -> None:
    """The ``cv2x-marl`` command: :func:`main`, then exit with its status; a signal that arrives after the command
    has ended (a second Ctrl-C) ends the process at once with that status (:func:`interrupts.exit_on_signal`)."""
    status = 1
    try:
        status = main()
    except KeyboardInterrupt:  # a signal while main put its handlers back
        status = 130
    finally:
        interrupts.exit_on_signal(status)
    sys.exit(status)


if __name__ == "__main__":
    console()
