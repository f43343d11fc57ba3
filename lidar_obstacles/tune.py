"""`lidar-obstacles tune`: search the obstacle detector's parameters on labelled inputs.

The space comes from the config schema (parameters declared ``tunable``, within their
declared ranges; ``--space FILE`` narrows it). Candidates are a scrambled Sobol sequence
(quasi-random: even coverage, reproducible by seed), the first being the start point (the
defaults or ``--start``). A candidate is stopped early when its score on the first input is
already far below the best candidate's there. The objective is maximised; wire and tower
points classified as ground are a hard constraint (a heavy penalty per point share).
The best candidate is written as a ROS 2 params YAML the nodes, `replay` and `evaluate`
load; the summary reports each parameter's sensitivity and the score on held-out inputs.
"""
from __future__ import annotations

import logging
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidar_obstacles.config import (
    ObstacleDetectorConfig,
    ParamInfo,
    coerce,
    dump_ros_yaml,
    flatten,
    load_params_file,
    params_of,
    read_yaml_file,
    replace,
)
from lidar_obstacles.errors import ConfigError
from lidar_obstacles.evaluate import LabelledInput, _concat, load_input, run_detector
from lidar_obstacles.io.atomic import YAML, atomic_write_text, check_replaceable

log = logging.getLogger(__name__)

EARLY_STOP_MARGIN = 0.05  # a candidate this far below the best on the first input stops
SAFETY_PENALTY = 10.0  # score lost per unit share of wire/tower points put in ground
LOWER_IS_BETTER = {"total_error"}  # objectives the score negates


def parse_budget(text: str) -> float:
    """'90s', '10m', '1.5h' or plain seconds -> seconds. ConfigError otherwise."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([smh]?)\s*", text)
    if not m:
        raise ConfigError(f"budget '{text}': expected a duration like 90s, 10m or 1h")
    if float(m.group(1)) <= 0:
        raise ConfigError(f"budget '{text}': must be more than 0 (no trial would run)")
    return float(m.group(1)) * {"": 1, "s": 1, "m": 60, "h": 3600}[m.group(2)]


@dataclass(frozen=True)
class Dimension:
    """One searched parameter: a numeric interval (log or linear) or a set of choices."""

    name: str
    low: float = 0.0
    high: float = 0.0
    choices: tuple[str, ...] = ()
    log: bool = False
    integer: bool = False

    def value(self, u: float) -> Any:
        """Map u in [0, 1) to a value of this dimension."""
        if self.choices:
            return self.choices[min(int(u * len(self.choices)), len(self.choices) - 1)]
        if self.log and self.low > 0:
            v = float(np.exp(np.log(self.low) + u * (np.log(self.high) - np.log(self.low))))
        else:
            v = self.low + u * (self.high - self.low)
        return int(round(v)) if self.integer else v


def _in_space_file(space_file: str | Path, info: ParamInfo, value: Any) -> Any:
    """`value` of parameter `info` as `coerce` takes it; its ConfigError names the space
    file (it named only the parameter, as if a params file were wrong)."""
    try:
        return coerce(info, value)
    except ConfigError as exc:
        raise ConfigError(f"space file {space_file}: {exc}") from None


def search_space(space_file: str | Path | None = None) -> list[Dimension]:
    """The tunable parameters of the obstacle detector, optionally narrowed by a YAML file
    ``{name: [min, max]}`` or ``{name: [choice, ...]}`` (names must be declared parameters,
    intervals inside the declared range)."""
    infos = {p.name: p for p in params_of(ObstacleDetectorConfig)}
    dims = {p.name: _dimension(p.name, p.spec.min, p.spec.max, p.spec.choices,
                               p.spec.log_scale, p.type is int)
            for p in infos.values() if p.spec.tunable}
    if space_file is not None:
        data = read_yaml_file(space_file, "space file") or {}
        if not isinstance(data, dict):
            raise ConfigError(f"space file {space_file}: expected a mapping of parameters")
        dims = {}
        for name, spec in data.items():
            info = infos.get(name)
            if info is None:
                raise ConfigError(f"space file {space_file}: unknown parameter '{name}'")
            if not isinstance(spec, list) or not spec:
                raise ConfigError(f"space file {space_file}: '{name}' needs a list")
            if info.spec.choices or info.type is bool:
                choices = tuple(spec)
                for c in choices:
                    _in_space_file(space_file, info, c)
                dims[name] = Dimension(name, choices=choices)
            else:
                if len(spec) != 2:
                    raise ConfigError(f"space file {space_file}: '{name}' needs [min, max]")
                low, high = (_in_space_file(space_file, info, v) for v in spec)
                if low > high:
                    raise ConfigError(f"space file {space_file}: '{name}' min > max")
                dims[name] = _dimension(name, low, high, (), info.spec.log_scale,
                                        info.type is int)
    if not dims:
        raise ConfigError("the search space is empty")
    return list(dims.values())


def _dimension(name, low, high, choices, log, integer) -> Dimension:
    if choices:
        return Dimension(name, choices=tuple(choices))
    return Dimension(name, float(low), float(high), log=bool(log), integer=integer)


def score_input(inp: LabelledInput, cfg: ObstacleDetectorConfig, objective: str, *,
                deadline: float | None = None) -> dict:
    """Run the detector on one input and score it. Returns "score" (higher is better: the
    objective, negated when lower is better, less SAFETY_PENALTY x the share of wire and
    tower points put in ground), "objective" (the objective itself, in its own sign; None
    when undefined), and the figures behind them. TimeoutError when time.monotonic()
    passes `deadline` before the input is done."""
    from lidar_obstacles.core.metrics import evaluate_classes

    run_detector(inp, cfg, deadline=deadline)
    _, ref, pred = _concat(inp)
    m = evaluate_classes(ref, pred)
    go = m["ground_object"]
    raw = {"ground_kappa": go["kappa"], "kappa": m["kappa"],
           "total_error": go["total_error"]}[objective]
    value = 0.0 if raw is None else -raw if objective in LOWER_IS_BETTER else raw
    unsafe = m["safety"]["obstacle_as_ground"] or 0.0
    return {"score": float(value - SAFETY_PENALTY * unsafe), "objective": raw,
            "ground_kappa": go["kappa"], "total_error": go["total_error"],
            "obstacle_as_ground": unsafe}


def _mean(values: list) -> float | None:
    """The mean of the defined values (None when there are none)."""
    defined = [v for v in values if v is not None]
    return float(np.mean(defined)) if defined else None


def _scored(inputs: list[LabelledInput], cfg, objective) -> dict:
    """Mean score and mean objective of one configuration over `inputs`."""
    runs = [score_input(i, cfg, objective) for i in inputs]
    return {"score": _mean([r["score"] for r in runs]),
            "objective": _mean([r["objective"] for r in runs])}


def tune(sources: list[Path], *, validate: list[Path] | None = None, out: Path,
         budget_s: float = 600.0, max_trials: int = 200, seed: int = 0,
         space_file: Path | None = None, start_file: Path | None = None,
         objective: str = "ground_kappa", topic: str | None = None,
         skip_malformed: bool = False) -> dict:
    """Search, write the best candidate as params YAML, return the summary. `topic`: the
    labelled bags' PointCloud2 topic (`load_input`'s). A malformed cloud of an input bag
    stops it unless `skip_malformed`."""
    from scipy.stats import qmc, spearmanr
    from tqdm import tqdm

    out = Path(out)
    if out.is_dir() or not out.parent.is_dir():  # said now, not after the whole search
        raise ConfigError(f"cannot write the params file {out}: "
                          + ("it is a folder" if out.is_dir() else
                             f"folder {out.parent} does not exist"))
    check_replaceable(out, YAML)
    dims = search_space(space_file)
    start = (load_params_file(start_file, ObstacleDetectorConfig, "obstacle_detector")
             if start_file else ObstacleDetectorConfig())
    sources = list(sources)
    if validate is None and len(sources) > 1:
        validate = [sources.pop()]  # guard against overfitting: keep one input unseen
    inputs = [load_input(p, topic=topic, cfg=start, skip_malformed=skip_malformed)
              for p in sources]
    held_out = [load_input(p, topic=topic, cfg=start, skip_malformed=skip_malformed)
                for p in (validate or [])]
    sobol = qmc.Sobol(d=len(dims), scramble=True, seed=seed)
    t_end = time.monotonic() + budget_s
    trials: list[dict] = []
    best: dict | None = None
    best_first = -np.inf
    bar = tqdm(total=max_trials, desc="tune", disable=None, file=sys.stderr)
    try:
        while len(trials) < max_trials and time.monotonic() < t_end:
            if not trials:
                updates = {d.name: flatten(start)[d.name] for d in dims}
            else:
                u = sobol.random(1)[0]
                updates = {d.name: d.value(float(x)) for d, x in zip(dims, u)}
            try:
                cfg = replace(start, updates)
            except ConfigError:
                continue  # a combination the schema rejects is simply not a candidate
            scores, objectives = [], []
            stopped = False
            # The budget holds inside a candidate too (between clouds), except for the
            # first, the start: there must be one scored candidate to write.
            try:
                for i, inp in enumerate(inputs):
                    run = score_input(inp, cfg, objective, deadline=t_end if trials else None)
                    scores.append(run["score"])
                    objectives.append(run["objective"])
                    if i == 0 and len(inputs) > 1:  # (with one input it is complete)
                        if scores[0] < best_first - EARLY_STOP_MARGIN:
                            stopped = True
                            break
                    if time.monotonic() > t_end and best is not None:
                        stopped = True
                        break
            except TimeoutError:
                break  # the budget ran out inside this candidate: it is not scored
            trial = {"params": updates, "score": float(np.mean(scores)),
                     "objective": _mean(objectives), "first_input_score": scores[0],
                     "stopped_early": stopped}
            trials.append(trial)
            if not stopped and (best is None or trial["score"] > best["score"]):
                best = trial
                best_first = max(best_first, scores[0])
            bar.update(1)
            bar.set_postfix(best=f"{best['score']:.4f}" if best else "-")
    finally:
        bar.close()
    if best is None:
        raise ConfigError("the budget ended before a single candidate was scored")
    best_cfg = replace(start, best["params"])
    check = None
    if held_out:  # before the file is written: a stop in this scoring leaves no file
        before = _scored(held_out, start, objective)
        after = _scored(held_out, best_cfg, objective)
        check = {"inputs": [i.name for i in held_out],
                 "start_score": before["score"], "best_score": after["score"],
                 "start_objective": before["objective"], "best_objective": after["objective"],
                 # the same configuration scores the same: neither better nor worse
                 "unchanged": best["params"] == trials[0]["params"]
                 or after["score"] == before["score"]}
        check["improved"] = not check["unchanged"] and after["score"] > before["score"]
    try:
        atomic_write_text(out, "# Written by `lidar-obstacles tune`: the best candidate of "
                          f"{len(trials)} on {', '.join(i.name for i in inputs)}.\n"
                          + dump_ros_yaml(best_cfg, "/**"), kind=YAML)
    except OSError as exc:
        raise ConfigError(f"cannot write the params file {out}: {exc}") from None
    complete = [t for t in trials if not t["stopped_early"]]
    sensitivity: dict[str, dict[str, Any]] = {}
    for d in dims:
        vals = [t["params"][d.name] for t in complete]
        ys = [t["score"] for t in complete]
        if d.choices:
            means = {c: float(np.mean([y for v, y in zip(vals, ys) if v == c]))
                     for c in d.choices if c in vals}
            sensitivity[d.name] = {"mean_score_by_choice": means}
        elif len(set(vals)) > 2:
            # the same score whatever the value: no effect (rho is undefined there)
            rho = spearmanr(vals, ys).statistic if len(set(ys)) > 1 else 0.0
            sensitivity[d.name] = {"spearman_rho": None if np.isnan(rho) else float(rho)}
    summary = {
        "params_file": str(out), "objective": objective, "trials": len(trials),
        "stopped_early": sum(t["stopped_early"] for t in trials),
        "start_score": trials[0]["score"], "best_score": best["score"],
        "start_objective": trials[0]["objective"], "best_objective": best["objective"],
        "best_params": best["params"], "sensitivity": sensitivity,
        "inputs": [i.name for i in inputs],
    }
    if check is not None:
        summary["validation"] = check
        if not check["improved"] and not check["unchanged"]:
            log.warning("tune: warning: the best candidate scores %.4f on the held-out "
                        "inputs, the start %.4f: it may fit only the tuning inputs (%s is "
                        "written all the same)", check["best_score"], check["start_score"], out)
    return summary
