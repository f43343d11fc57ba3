"""Evaluation metrics of ``lidar-obstacles evaluate``: pure NumPy, JSON-ready results.

Everything here compares a prediction with a reference and returns plain dicts whose keys
are stable (the CLI prints them as JSON, the report renders them). Rates and accuracies are
fractions in [0, 1], never percent. A value that is undefined for the data (a division by
zero: no point of a class, one class only, a constant reference) is ``None`` (JSON
``null``), never NaN, so every result passes ``json.dumps(..., allow_nan=False)``.

Class groups
------------
Reference and prediction are ASPRS codes; they are compared as groups (:data:`GROUPS`):

=========== ========================= =================================================
group       ASPRS codes               why
=========== ========================= =================================================
ground      2, 8, 9, 11               ground-level surfaces a DEM is built from: ground,
                                      model key-point (a thinned ground subset), water,
                                      road surface
vegetation  3, 4, 5                   low / medium / high vegetation
building    6                         building
wire        13, 14                    wire: guard / shield, conductor
tower       15, 16                    transmission tower, and the wire's connectors
                                      and insulators on it
other       everything else           1 unclassified obstacle, 7 noise, 0 (ISPRS
                                      reference "object"), 26 crane, ...
=========== ========================= =================================================

The ground/object figures (Type I/II) split the same way: ground = group ``ground``,
object = every other group (noise included: it is not ground).

Confusion-matrix orientation
----------------------------
Rows are the PREDICTED group (the map), columns the REFERENCE group, as in the remote
sensing literature (Congalton 1991; Story & Congalton 1986) and in methods.md: with
q_ij = points predicted as i whose reference is j, row totals Q_i+ and column totals Q_+i,

- user's accuracy of class i     = q_ii / Q_i+  (of the points labelled i, the share that is i)
- producer's accuracy of class i = q_ii / Q_+i  (of the reference i, the share found as i)

NOTE: scikit-learn's ``confusion_matrix`` is the transpose (rows = reference).

JSON keys of :func:`evaluate_classes`
-------------------------------------
============================================ ================================================
key                                          meaning
============================================ ================================================
``n_points``                                 points compared (int)
``groups``                                   the group names, order of the matrix (list)
``reference_classes_objects``                False when the reference tells ground from
                                             object only (every object 0 or 1, as ISPRS):
                                             the predicted objects then count as `other`
                                             (:func:`compared_groups`)
``merged_into_other``                        the predicted groups counted as `other`, as
                                             the reference does not class them (list:
                                             ISPRS all four object groups, AHN4
                                             ``["vegetation"]``, else empty)
``confusion.rows`` / ``.columns``            ``"predicted"`` / ``"reference"``
``confusion.labels``                         group names of rows and columns (list)
``confusion.matrix``                         counts q_ij, rows predicted, columns reference
``overall_accuracy``                         P_c = sum q_ii / Q
``kappa``                                    Cohen's kappa over all groups
``per_class.<group>.reference_count``        Q_+i
``per_class.<group>.predicted_count``        Q_i+
``per_class.<group>.users_accuracy``         q_ii / Q_i+ (None when Q_i+ = 0)
``per_class.<group>.producers_accuracy``     q_ii / Q_+i (None when Q_+i = 0)
``per_class.<group>.users_kappa``            conditional kappa, user's side
``per_class.<group>.producers_kappa``        conditional kappa, producer's side
``ground_object.n_ground`` / ``.n_object``   reference ground / object points
``ground_object.type_i``                     ground rejected / reference ground
``ground_object.type_ii``                    objects accepted as ground / reference objects
``ground_object.total_error``                misclassified (ground vs object) / all
``ground_object.kappa``                      Cohen's kappa of the 2 x 2 ground/object table
``ground_object.matrix``                     [[ground->ground, object->ground],
                                              [ground->object, object->object]]
                                             (rows predicted, columns reference)
``blocks``                                   None without ``xy``; else:
``blocks.nx`` / ``.ny``                      grid columns (x) / rows (y)
``blocks.extent``                            [xmin, xmax, ymin, ymax], metres
``blocks.min_class_share``                   eligibility threshold (0.05)
``blocks.kappa``                             (ny, nx) ground/object kappa, row 0 = south
                                             (min y), None where not eligible
``blocks.n_points``                          (ny, nx) points per block
``blocks.n_blocks`` / ``.n_eligible``        all blocks / eligible blocks
``blocks.share_kappa_gt_0_8``                eligible blocks with kappa > 0.8 / eligible
``blocks.share_kappa_gt_0_6``                eligible blocks with kappa > 0.6 / eligible
``blocks.mean_kappa``                        mean kappa of the eligible blocks
``safety.n_wire`` / ``.n_tower``             reference wire (13, 14) / tower (15, 16) points
``safety.wire_as_ground``                    wire points predicted ground / wire points
``safety.tower_as_ground``                   tower points predicted ground / tower points
``safety.obstacle_as_ground``                both together
``safety.n_raised_object``                   (with a reference DEM: ``raised_objects_as_ground``)
                                             reference objects of any class more than 1 m
                                             above the reference ground
``safety.raised_object_as_ground``           those predicted ground / those
``by_code.<reference code>.<predicted code>`` points of that reference ASPRS code predicted
                                             as that code (nonzero pairs only; codes as
                                             strings): where a class the groups lump
                                             together went (the corridor's cranes, 26)
============================================ ================================================

Other functions: :func:`grid_errors` (keys ``n``, ``rmse_m``, ``mae_m``, ``bias_m``,
``max_abs_m``, ``r2``), :func:`raster_correlation` (a float), :func:`latency_stats`
(keys ``n``, ``mean_s``, ``p50_s``, ``p95_s``, ``p99_s``, ``max_s``).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from lidar_obstacles.core.classes import TOWER, WIRE
from lidar_obstacles.errors import CloudFormatError, ConfigError

WIRE_CODES = (13, WIRE)  # ASPRS: wire - guard (shield), wire - conductor (phase)
TOWER_CODES = (TOWER, 16)  # transmission tower, wire - structure connector (insulator)

GROUPS: tuple[str, ...] = ("ground", "vegetation", "building", "wire", "tower", "other")
"""Names of the evaluation groups; index i of a group is its row/column in the matrices."""

# Group indices, named apart from the ASPRS codes of core.classes (GROUND there is 2)
GROUP_GROUND, GROUP_VEGETATION, GROUP_BUILDING, GROUP_WIRE, GROUP_TOWER, GROUP_OTHER = range(
    len(GROUPS))

GROUND_CODES: tuple[int, ...] = (2, 8, 9, 11)
"""ASPRS codes read as ground level (ground, model key-point, water, road surface)."""

_CODE_TO_GROUP = np.full(256, GROUP_OTHER, dtype=np.int64)
_CODE_TO_GROUP[list(GROUND_CODES)] = GROUP_GROUND
_CODE_TO_GROUP[[3, 4, 5]] = GROUP_VEGETATION
_CODE_TO_GROUP[6] = GROUP_BUILDING
# (the detector labels every wire 14 and every tower 15; a reference with shield wires (13)
# or insulators (16) is compared with them: a shield wire put in ground is a wire missed)
_CODE_TO_GROUP[list(WIRE_CODES)] = GROUP_WIRE
_CODE_TO_GROUP[list(TOWER_CODES)] = GROUP_TOWER


# --------------------------------------------------------------------------- helpers


def _ratio(num: float, den: float) -> float | None:
    """num / den as a Python float, None when den is 0 (undefined, not an error)."""
    return float(num) / float(den) if den else None


def _as_codes(classes: Any, name: str) -> np.ndarray:
    """(N,) int64 ASPRS codes in 0..255, or CloudFormatError naming the argument."""
    arr = np.asarray(classes)
    if arr.ndim != 1:
        raise CloudFormatError(f"{name}: expected a 1-D array of class codes, got shape "
                               f"{arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        if not np.issubdtype(arr.dtype, np.floating) or not np.all(np.isfinite(arr)) or np.any(
            arr != np.round(arr)
        ):
            raise CloudFormatError(f"{name}: class codes must be integers, got dtype {arr.dtype}")
    codes = arr.astype(np.int64, copy=False)
    if codes.size and (codes.min() < 0 or codes.max() > 255):
        raise CloudFormatError(
            f"{name}: class codes must lie in 0..255, got {codes.min()}..{codes.max()}"
        )
    return codes


def code_crosstab(reference: np.ndarray, predicted: np.ndarray) -> dict[str, dict[str, int]]:
    """{reference code: {predicted code: points}} of (N,) int64 ASPRS codes in 0..255, the
    nonzero pairs only, codes as strings (JSON keys), in ascending order."""
    pairs, counts = np.unique(reference * 256 + predicted, return_counts=True)
    out: dict[str, dict[str, int]] = {}
    for pair, n in zip(pairs.tolist(), counts.tolist()):  # at most 256 x 256 pairs
        out.setdefault(str(pair // 256), {})[str(pair % 256)] = n
    return out


def group_of(classes: Any) -> np.ndarray:
    """Evaluation group of each point.

    classes: (N,) integer ASPRS codes (0..255).
    Returns (N,) int64 indices into :data:`GROUPS`.
    """
    return _CODE_TO_GROUP[_as_codes(classes, "classes")]


def compared_groups(reference: Any, predicted: Any
                    ) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """(reference groups (N,), predicted groups (N,), the predicted groups counted as
    `other`) of (N,) ASPRS codes each, as :func:`evaluate_classes` compares them.

    A reference cannot say an object's class is wrong where it does not class such
    objects, and then the predicted objects of those groups count as `other`:
    - a reference that tells ground from object only (ISPRS: every object 0 or 1, none
      vegetation, building, wire or tower): all four groups (a vegetation point was
      "wrong" against ISPRS's "object", and samp11 scored overall accuracy 0.55, kappa
      0.31, for total error 8.5 %, kappa 0.83);
    - a reference with `other` objects but no vegetation (AHN4: 1 "other, mostly
      vegetation", 2 ground, 6 building): vegetation (the AHN4 tile's trees, found as
      such, were 21.8 % of its points "of the wrong class").
    Buildings, wires and towers a reference lacks are not merged: a scene may hold none
    (the simulator's corridor has no building), and one found there is wrong."""
    ref, pred = group_of(reference), group_of(predicted)
    present = np.zeros(len(GROUPS), bool)
    present[np.unique(ref)] = True
    objects = (GROUP_VEGETATION, GROUP_BUILDING, GROUP_WIRE, GROUP_TOWER)
    if not present[list(objects)].any():
        merged: tuple[int, ...] = objects
    elif present[GROUP_OTHER] and not present[GROUP_VEGETATION]:
        merged = (GROUP_VEGETATION,)
    else:
        merged = ()
    if merged:
        pred = np.where(np.isin(pred, merged), GROUP_OTHER, pred)
    return ref, pred, tuple(GROUPS[g] for g in merged)


def parse_blocks(spec: str | tuple[int, int]) -> tuple[int, int]:
    """``"6x6"`` (columns x rows) or ``(nx, ny)`` -> ``(nx, ny)``; ConfigError otherwise."""
    if isinstance(spec, str):
        parts = spec.lower().replace(" ", "").split("x")
        if len(parts) != 2 or not all(p.isdigit() for p in parts):
            raise ConfigError(f"blocks: expected 'NXxNY' such as '6x6', got {spec!r}")
        nx, ny = int(parts[0]), int(parts[1])
    else:
        try:
            nx, ny = (int(v) for v in spec)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"blocks: expected (nx, ny), got {spec!r}") from exc
    if not (1 <= nx <= 1000 and 1 <= ny <= 1000):
        raise ConfigError(f"blocks: nx and ny must lie in 1..1000, got {nx}x{ny}")
    return nx, ny


def jsonable(value: Any) -> Any:
    """A copy of ``value`` made of dict/list/str/int/float/bool/None only.

    NumPy scalars and arrays become Python numbers and lists, tuples become lists,
    non-finite floats become None (strict JSON has no NaN). Raises TypeError for anything
    else, so a programming mistake does not silently vanish from a report.
    """
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if hasattr(value, "__fspath__"):
        return str(value)
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")


# --------------------------------------------------------------------------- confusion


def confusion_matrix(reference: np.ndarray, predicted: np.ndarray, n_classes: int) -> np.ndarray:
    """Counts q_ij of points predicted as i whose reference is j.

    reference, predicted: (N,) int indices in 0..n_classes-1.
    Returns (n_classes, n_classes) int64, rows = predicted, columns = reference.
    """
    flat = predicted.astype(np.int64) * n_classes + reference.astype(np.int64)
    return np.bincount(flat, minlength=n_classes * n_classes).reshape(n_classes, n_classes)


def kappa_from_confusion(matrix: np.ndarray) -> float | None:
    """Cohen's kappa of a square confusion matrix (either orientation).

    kappa = (P_o - P_e) / (1 - P_e), P_o = sum q_ii / Q, P_e = sum Q_i+ Q_+i / Q^2.
    None when P_e = 1, i.e. reference and prediction put every point in the same single
    class: agreement is then total but entirely expected by chance, so kappa is undefined
    (scikit-learn returns NaN with a warning in that case). None also for Q = 0.
    """
    m = np.asarray(matrix, dtype=np.float64)
    total = m.sum()
    if total == 0:
        return None
    p_o = np.trace(m) / total
    p_e = float(m.sum(axis=1) @ m.sum(axis=0)) / total**2
    # P_e = 1 needs both marginals on one class, hence P_o = 1; test with a tolerance
    # because P_e is a float sum.
    if 1.0 - p_e <= 1e-12:
        return None
    return float((p_o - p_e) / (1.0 - p_e))


def _conditional_kappas(matrix: np.ndarray) -> tuple[list[float | None], list[float | None]]:
    """User's and producer's conditional kappa per class (Rosenfield & Fitzpatrick-Lins 1986).

    With rows = predicted (map) and columns = reference, Q points, q_ii the diagonal:

        user's     kappa_i = (Q q_ii - Q_i+ Q_+i) / (Q Q_i+ - Q_i+ Q_+i)
        producer's kappa_i = (Q q_ii - Q_i+ Q_+i) / (Q Q_+i - Q_i+ Q_+i)

    The user's version is the agreement, beyond chance, of the points mapped as i; the
    producer's that of the reference points of i. Undefined (None) when the denominator
    is 0: the class is absent from that side, or it holds every point.
    """
    m = np.asarray(matrix, dtype=np.float64)
    q = m.sum()
    diag = np.diag(m)
    rows = m.sum(axis=1)
    cols = m.sum(axis=0)
    num = q * diag - rows * cols
    den_user = q * rows - rows * cols
    den_prod = q * cols - rows * cols
    users = [_ratio(n, d) for n, d in zip(num, den_user)]
    producers = [_ratio(n, d) for n, d in zip(num, den_prod)]
    return users, producers


RAISED_OBJECT_HEIGHT = 1.0  # m: an object this high a UAV flying low must never take for ground


def raised_objects_as_ground(reference_classes: Any, predicted_classes: Any,
                             height_above_reference: Any) -> dict:
    """What a low-flying UAV must never be told is ground, over every class (the wires'
    and towers' `safety` figures cover two): the reference objects (any group but ground)
    standing more than RAISED_OBJECT_HEIGHT above the reference ground, and the share of
    them predicted ground. height_above_reference: (N,) m, each point's height above the
    DEM of the reference ground (NaN where it has none: not counted). Returns
    {"n_raised_object": n, "raised_object_as_ground": share, None when n = 0}."""
    ref = _as_codes(reference_classes, "reference_classes")
    pred = _as_codes(predicted_classes, "predicted_classes")
    height = np.asarray(height_above_reference, np.float64)
    if not ref.shape == pred.shape == height.shape:
        raise ConfigError(f"raised_objects_as_ground: {ref.shape}, {pred.shape} and "
                          f"{height.shape} points")
    raised = (_CODE_TO_GROUP[ref] != GROUP_GROUND) & (height > RAISED_OBJECT_HEIGHT)
    n = int(raised.sum())
    return {"n_raised_object": n, "raised_object_as_ground":
            _ratio(int((raised & (_CODE_TO_GROUP[pred] == GROUP_GROUND)).sum()), n)}


def ground_object_errors(reference_ground: np.ndarray, predicted_ground: np.ndarray) -> dict:
    """ISPRS filter-test errors of a ground/object split (Sithole & Vosselman 2004).

    reference_ground, predicted_ground: (N,) bool, True where the point is ground.
    Returns the ``ground_object`` dict of :func:`evaluate_classes`:
    Type I = ground points rejected / reference ground, Type II = object points accepted
    as ground / reference objects, total error = both / N, kappa of the 2 x 2 table.
    """
    ref = np.asarray(reference_ground, dtype=bool)
    pred = np.asarray(predicted_ground, dtype=bool)
    if ref.shape != pred.shape or ref.ndim != 1:
        raise CloudFormatError(
            f"ground masks must be 1-D of equal length, got {ref.shape} and {pred.shape}"
        )
    # index 0 = ground, 1 = object, rows predicted, columns reference
    matrix = confusion_matrix((~ref).astype(np.int64), (~pred).astype(np.int64), 2)
    n_ground = int(matrix[:, 0].sum())
    n_object = int(matrix[:, 1].sum())
    type_i = int(matrix[1, 0])
    type_ii = int(matrix[0, 1])
    return {
        "n_ground": n_ground,
        "n_object": n_object,
        "type_i": _ratio(type_i, n_ground),
        "type_ii": _ratio(type_ii, n_object),
        "total_error": _ratio(type_i + type_ii, ref.size),
        "kappa": kappa_from_confusion(matrix),
        "matrix": matrix.tolist(),
    }


# --------------------------------------------------------------------------- blocks


def block_kappa(
    xy: np.ndarray,
    reference_ground: np.ndarray,
    predicted_ground: np.ndarray,
    *,
    blocks: str | tuple[int, int] = (6, 6),
    min_class_share: float = 0.05,
) -> dict:
    """Ground/object kappa per block of an ``nx x ny`` grid over the points' extent.

    xy: (N, 2) float64, metres. reference_ground, predicted_ground: (N,) bool.
    blocks: ``(nx, ny)`` or ``"6x6"``; blocks are equal rectangles over [xmin, xmax] x
    [ymin, ymax], row 0 the southernmost (min y), points on the far edge go to the last
    block. A block is eligible when reference ground and reference object each hold at
    least ``min_class_share`` of its points (a block that is all ground has an undefined
    or meaningless kappa; seed 004 judged its 36 blocks the same way).
    Returns the ``blocks`` dict of :func:`evaluate_classes`.
    """
    nx, ny = parse_blocks(blocks)
    if not 0.0 <= min_class_share <= 0.5:
        raise ConfigError(f"min_class_share must lie in 0..0.5, got {min_class_share}")
    xy = np.asarray(xy, dtype=np.float64)
    ref = np.asarray(reference_ground, dtype=bool)
    pred = np.asarray(predicted_ground, dtype=bool)
    if xy.ndim != 2 or xy.shape[1] < 2 or xy.shape[0] != ref.size or ref.shape != pred.shape:
        raise CloudFormatError(
            f"xy must be (N, 2) with N = {ref.size} matching the classes, got {xy.shape}"
        )
    if ref.size == 0:
        raise CloudFormatError("no points to evaluate")
    if not np.all(np.isfinite(xy[:, :2])):
        raise CloudFormatError("xy contains NaN or infinite coordinates")
    lo = xy[:, :2].min(axis=0)
    hi = xy[:, :2].max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    ix = np.minimum(((xy[:, 0] - lo[0]) / span[0] * nx).astype(np.int64), nx - 1)
    iy = np.minimum(((xy[:, 1] - lo[1]) / span[1] * ny).astype(np.int64), ny - 1)
    cell = iy * nx + ix
    # one 2 x 2 table per block: key = block * 4 + predicted_object * 2 + reference_object
    key = cell * 4 + (~pred).astype(np.int64) * 2 + (~ref).astype(np.int64)
    tables = np.bincount(key, minlength=nx * ny * 4).reshape(nx * ny, 2, 2).astype(np.float64)
    n = tables.sum(axis=(1, 2))
    ref_ground = tables[:, :, 0].sum(axis=1)
    ref_object = n - ref_ground
    pred_ground = tables[:, 0, :].sum(axis=1)
    pred_object = n - pred_ground
    with np.errstate(divide="ignore", invalid="ignore"):
        p_o = (tables[:, 0, 0] + tables[:, 1, 1]) / n
        p_e = (pred_ground * ref_ground + pred_object * ref_object) / n**2
        kappa = (p_o - p_e) / (1.0 - p_e)
        eligible = ((n > 0) & (ref_ground >= min_class_share * n)
                    & (ref_object >= min_class_share * n))
    # Eligible blocks have both reference classes, so P_e < 1 and kappa is finite.
    kappa = np.where(eligible, kappa, np.nan)
    good = kappa[eligible]
    n_eligible = int(eligible.sum())
    return {
        "nx": nx,
        "ny": ny,
        "extent": [float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])],
        "min_class_share": float(min_class_share),
        "kappa": jsonable(kappa.reshape(ny, nx)),
        "n_points": n.astype(np.int64).reshape(ny, nx).tolist(),
        "n_blocks": nx * ny,
        "n_eligible": n_eligible,
        "share_kappa_gt_0_8": _ratio(int((good > 0.8).sum()), n_eligible),
        "share_kappa_gt_0_6": _ratio(int((good > 0.6).sum()), n_eligible),
        "mean_kappa": float(good.mean()) if n_eligible else None,
    }


# --------------------------------------------------------------------------- classes


def evaluate_classes(
    reference_classes: Any,
    predicted_classes: Any,
    *,
    xy: np.ndarray | None = None,
    blocks: str | tuple[int, int] = (6, 6),
    min_class_share: float = 0.05,
) -> dict:
    """Compare predicted with reference ASPRS classes; all figures of seed 004 and ISPRS.

    reference_classes, predicted_classes: (N,) integer ASPRS codes of the same points.
    xy: optional (N, 2) float64 horizontal coordinates, metres, for the per-block kappa.
    blocks: grid of the per-block kappa, ``(nx, ny)`` or ``"6x6"``.
    min_class_share: a block is eligible when reference ground and object each hold at
        least this share of its points.
    Returns a JSON-ready dict; its keys are listed in the module docstring.
    Raises CloudFormatError for arrays of different lengths, no points, non-integer codes.
    """
    ref_codes = _as_codes(reference_classes, "reference_classes")
    pred_codes = _as_codes(predicted_classes, "predicted_classes")
    if ref_codes.size != pred_codes.size:
        raise CloudFormatError(
            f"reference has {ref_codes.size} points but prediction has {pred_codes.size}"
        )
    if ref_codes.size == 0:
        raise CloudFormatError("no points to evaluate")
    ref, pred, merged = compared_groups(ref_codes, pred_codes)
    k = len(GROUPS)
    matrix = confusion_matrix(ref, pred, k)
    total = int(matrix.sum())
    rows = matrix.sum(axis=1)
    cols = matrix.sum(axis=0)
    users_kappa, producers_kappa = _conditional_kappas(matrix)
    per_class = {
        name: {
            "reference_count": int(cols[i]),
            "predicted_count": int(rows[i]),
            "users_accuracy": _ratio(matrix[i, i], rows[i]),
            "producers_accuracy": _ratio(matrix[i, i], cols[i]),
            "users_kappa": users_kappa[i],
            "producers_kappa": producers_kappa[i],
        }
        for i, name in enumerate(GROUPS)
    }
    ref_ground = ref == GROUP_GROUND
    pred_ground = pred == GROUP_GROUND
    is_wire = _CODE_TO_GROUP[ref_codes] == GROUP_WIRE
    is_tower = _CODE_TO_GROUP[ref_codes] == GROUP_TOWER
    n_wire = int(is_wire.sum())
    n_tower = int(is_tower.sum())
    wire_hit = int((is_wire & pred_ground).sum())
    tower_hit = int((is_tower & pred_ground).sum())
    return {
        "n_points": total,
        "groups": list(GROUPS),
        "reference_classes_objects": len(merged) < 4,
        "merged_into_other": list(merged),
        "confusion": {
            "rows": "predicted",
            "columns": "reference",
            "labels": list(GROUPS),
            "matrix": matrix.tolist(),
        },
        "overall_accuracy": _ratio(np.trace(matrix), total),
        "kappa": kappa_from_confusion(matrix),
        "per_class": per_class,
        "ground_object": ground_object_errors(ref_ground, pred_ground),
        "blocks": None if xy is None else block_kappa(
            xy, ref_ground, pred_ground, blocks=blocks, min_class_share=min_class_share),
        "safety": {
            "n_wire": n_wire,
            "n_tower": n_tower,
            "wire_as_ground": _ratio(wire_hit, n_wire),
            "tower_as_ground": _ratio(tower_hit, n_tower),
            "obstacle_as_ground": _ratio(wire_hit + tower_hit, n_wire + n_tower),
        },
        "by_code": code_crosstab(ref_codes, pred_codes),
    }


# --------------------------------------------------------------------------- DEM, rasters


def _paired_finite(reference: Any, estimate: Any, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Flattened float64 values of two same-shaped arrays where both are finite."""
    a = np.asarray(reference, dtype=np.float64)
    b = np.asarray(estimate, dtype=np.float64)
    if a.shape != b.shape:
        raise CloudFormatError(f"{what}: shapes differ, {a.shape} and {b.shape}")
    ok = np.isfinite(a) & np.isfinite(b)
    return a[ok], b[ok]


def grid_errors(reference: Any, estimate: Any) -> dict:
    """Height errors of a DEM (or any estimate) against a reference, NaN-aware.

    reference, estimate: arrays of the same shape, metres: two (rows, cols) grids, or
        (M,) check-point heights and the DEM heights at those points. Cells or points
        where either is NaN/inf are left out.
    Returns ``n`` (values compared), ``rmse_m`` = sqrt(mean (e - r)^2), ``mae_m``,
    ``bias_m`` = mean (e - r), ``max_abs_m``, and ``r2`` = 1 - SS_res / SS_tot with
    SS_tot about the reference mean (the coefficient of determination of seed 000/003;
    it can be negative). Every value is None when n = 0, r2 also when the reference is
    constant.
    """
    ref, est = _paired_finite(reference, estimate, "grid_errors")
    n = int(ref.size)
    if n == 0:
        return {"n": 0, "rmse_m": None, "mae_m": None, "bias_m": None, "max_abs_m": None,
                "r2": None}
    err = est - ref
    ss_res = float(err @ err)
    dev = ref - ref.mean()
    ss_tot = float(dev @ dev)
    return {
        "n": n,
        "rmse_m": math.sqrt(ss_res / n),
        "mae_m": float(np.abs(err).mean()),
        "bias_m": float(err.mean()),
        "max_abs_m": float(np.abs(err).max()),
        "r2": 1.0 - ss_res / ss_tot if ss_tot > 0 else None,
    }


def raster_correlation(a: Any, b: Any) -> float | None:
    """Pearson r of two rasters of the same shape over the cells finite in both.

    Seed 002 validates a simplified cloud by correlating its rasterised TIN with that of
    the full cloud. None when fewer than 2 cells are common or either raster is constant
    there, but for rounding: a TIN of a flat cloud at z = 100.3 m varies by 4e-14 m, and
    the r of that noise was any number (0.70, -0.003).
    """
    x, y = _paired_finite(a, b, "raster_correlation")
    if x.size < 2 or any(np.ptp(v) <= 1e-12 * np.abs(v).max() for v in (x, y)):
        return None
    x = x - x.mean()
    y = y - y.mean()
    den = math.sqrt(float(x @ x) * float(y @ y))
    return float(x @ y) / den if den > 0 else None


def grid_values_at(
    elevation: Any,
    xy: Any,
    *,
    resolution: float,
    origin: tuple[float, float],
) -> np.ndarray:
    """Bilinear heights of a grid at points, for DEM errors at check points.

    elevation: (rows, cols) float, metres, NaN = unknown; cell (r, c) covers
        x in [ox + c res, ox + (c+1) res), y in [oy + r res, oy + (r+1) res) (row 0 south,
        the nav_msgs/MapMetaData and grid_map convention), its value sits at the centre.
    xy: (M, 2) float64, metres. resolution: m/cell. origin: (ox, oy), metres.
    Returns (M,) float64; NaN outside the cell centres' hull or next to an unknown cell.
    """
    grid = np.asarray(elevation, dtype=np.float64)
    pts = np.asarray(xy, dtype=np.float64)
    if grid.ndim != 2:
        raise CloudFormatError(f"elevation must be (rows, cols), got shape {grid.shape}")
    if pts.ndim != 2 or pts.shape[1] < 2:
        raise CloudFormatError(f"xy must be (M, 2), got shape {pts.shape}")
    if not resolution > 0:
        raise ConfigError(f"resolution must be > 0 m, got {resolution}")
    rows, cols = grid.shape
    fc = (pts[:, 0] - origin[0]) / resolution - 0.5
    fr = (pts[:, 1] - origin[1]) / resolution - 0.5
    out = np.full(pts.shape[0], np.nan)
    inside = (fc >= 0) & (fr >= 0) & (fc <= cols - 1) & (fr <= rows - 1)
    if not inside.any():
        return out
    fc, fr = fc[inside], fr[inside]
    c0 = np.minimum(np.floor(fc).astype(np.int64), max(cols - 2, 0))
    r0 = np.minimum(np.floor(fr).astype(np.int64), max(rows - 2, 0))
    c1 = np.minimum(c0 + 1, cols - 1)
    r1 = np.minimum(r0 + 1, rows - 1)
    tc = fc - c0
    tr = fr - r0
    z = (
        grid[r0, c0] * (1 - tc) * (1 - tr)
        + grid[r0, c1] * tc * (1 - tr)
        + grid[r1, c0] * (1 - tc) * tr
        + grid[r1, c1] * tc * tr
    )
    out[inside] = z
    return out


# --------------------------------------------------------------------------- latency


def latency_stats(latencies_s: Any) -> dict:
    """Percentiles of per-message processing times.

    latencies_s: (M,) seconds; NaN entries are ignored.
    Returns ``n``, ``mean_s``, ``p50_s``, ``p95_s``, ``p99_s``, ``max_s`` (seconds,
    linear-interpolated percentiles); the figures are None when there is no latency.
    """
    lat = np.asarray(latencies_s, dtype=np.float64).ravel()
    lat = lat[np.isfinite(lat)]
    if lat.size == 0:
        return {"n": 0, "mean_s": None, "p50_s": None, "p95_s": None, "p99_s": None, "max_s": None}
    p50, p95, p99 = np.percentile(lat, [50, 95, 99])
    return {
        "n": int(lat.size),
        "mean_s": float(lat.mean()),
        "p50_s": float(p50),
        "p95_s": float(p95),
        "p99_s": float(p99),
        "max_s": float(lat.max()),
    }
