"""The measurement plan: what is probed, what is looked for, what is reported.

A plan is a TOML file (format in ``docs/plan.md``)::

    [plan]
    name = "Table 3"

    [[control]]                 # common control points: seen by the cameras
    id = "C1"                   # and probed by the CMM arm

    [[target]]                  # measured target points, found after registration
    id = "P1"                   # as the camera point nearest the nominal
    nominal = [12.0, -4.0, 3.5] # global position (mm) within search_radius (mm)
    search_radius = 3.0

    [[reference_point]]         # out-of-view reference points, probed once
    id = "R1"

    [[reference_line]]          # out-of-view axes, fitted to `probes` points
    id = "L3"
    probes = 8
    fit = "cylinder"            # "cylinder" (points on the surface) or "line"

    [[characteristic]]
    name = "P1-L3"
    kind = "point_line"         # point_point | point_line | depth
    a = "P1"
    b = "L3"
    nominal = 308.35            # mm
    tolerance = 0.1             # mm, symmetric (or upper_tol / lower_tol)

    [uncertainty]               # optional (docs/uncertainty.md)
    coverage_factor = 2.0       # k of U = k u_c
    decision_rule = "simple"    # simple | guarded_acceptance | guarded_rejection

    [temperature]               # optional: correction to 20 degC (ISO 1)
    part = 21.5                 # degC, with u_part (K), part_alpha (1/K), ...

    [job]                       # optional: the report's job header
    part = "Housing 4711"

The CMM arm probes the elements in ``probing_order`` (default: controls,
then reference points, then reference lines), one button press per point;
line probes are labelled ``L3.1 ... L3.n``.
"""

from __future__ import annotations

import hashlib
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from crossfield.errors import ConfigError
from crossfield.types import frozen_array
from crossfield.uncertainty.decision import RULES
from crossfield.uncertainty.temperature import Temperature

__all__ = [
    "Instrument",
    "JobHeader",
    "UncertaintySpec",
    "KINDS",
    "LINE_FITS",
    "CharacteristicSpec",
    "MeasurementPlan",
    "ReferenceLineSpec",
    "TargetSpec",
    "load_plan",
    "parse_plan",
]

KINDS = ("point_point", "point_line", "depth")
LINE_FITS = ("cylinder", "line")


@dataclass(frozen=True)
class TargetSpec:
    """A measured target point: nominal (3,) global mm, search radius mm."""

    id: str
    nominal: np.ndarray
    search_radius_mm: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "nominal", frozen_array(self.nominal, shape=(3,)))


@dataclass(frozen=True)
class ReferenceLineSpec:
    id: str
    probes: int
    fit: str


@dataclass(frozen=True)
class CharacteristicSpec:
    """kind: point_point (|a-b|), point_line (distance of point a to line b),
    depth (global Z of point a). nominal and tolerances in mm: the zone is
    ``[nominal - lower_tol, nominal + upper_tol]``; tolerance_mm is the
    symmetric tolerance (the larger of the two when they differ)."""

    name: str
    kind: str
    a: str
    b: str | None
    nominal_mm: float
    tolerance_mm: float
    upper_tol_mm: float | None = None
    lower_tol_mm: float | None = None

    def __post_init__(self) -> None:
        if self.upper_tol_mm is None:
            object.__setattr__(self, "upper_tol_mm", self.tolerance_mm)
        if self.lower_tol_mm is None:
            object.__setattr__(self, "lower_tol_mm", self.tolerance_mm)


@dataclass(frozen=True)
class UncertaintySpec:
    """How uncertainties are stated and decisions made (``docs/uncertainty.md``).

    coverage_factor: k of U = k u_c. decision_rule: ISO 14253-1 rule
    (:data:`crossfield.uncertainty.decision.RULES`). calibration_scale_u:
    relative scale uncertainty of the calibration when its file states none
    (None = :data:`crossfield.uncertainty.calibration.DEFAULT_SCALE_U`).
    target_radius_mm, max_tilt_deg: circle targets' radius (mm) and largest
    tilt to the line of sight (deg) for the eccentricity term (0 = no term).
    eccentricity_corrected: the centroids are corrected for eccentricity; the
    term is then the residual fraction ``eccentricity_residual`` of the bias.
    consistency_alpha: level of the residual chi-square test.
    """

    coverage_factor: float = 2.0
    decision_rule: str = "simple"
    calibration_scale_u: float | None = None
    target_radius_mm: float = 0.0
    max_tilt_deg: float = 0.0
    eccentricity_corrected: bool = False
    eccentricity_residual: float = 0.1
    consistency_alpha: float = 0.05


@dataclass(frozen=True)
class Instrument:
    """An instrument of the job header: id, kind (e.g. "CMM arm"), calibration date and due date (text)."""

    id: str
    kind: str = ""
    calibrated: str = ""
    due: str = ""


@dataclass(frozen=True)
class JobHeader:
    """The report's job header: part, serial number, operator, order, instruments."""

    part: str = ""
    serial: str = ""
    operator: str = ""
    order: str = ""
    instruments: tuple[Instrument, ...] = ()

    @property
    def stated(self) -> bool:
        return bool(self.part or self.serial or self.operator or self.order or self.instruments)


@dataclass(frozen=True)
class MeasurementPlan:
    name: str
    control_ids: tuple[str, ...]
    targets: tuple[TargetSpec, ...]
    reference_point_ids: tuple[str, ...]
    reference_lines: tuple[ReferenceLineSpec, ...]
    characteristics: tuple[CharacteristicSpec, ...]
    order: tuple[str, ...]
    source: str = ""
    text: str = ""
    uncertainty: UncertaintySpec = UncertaintySpec()
    temperature: Temperature = Temperature()
    job: JobHeader = JobHeader()

    def probing_order(self) -> list[str]:
        """Labels of the CMM points in the order the arm takes them."""
        lines = {line.id: line for line in self.reference_lines}
        labels: list[str] = []
        for element in self.order:
            if element in lines:
                labels.extend(f"{element}.{k}" for k in range(1, lines[element].probes + 1))
            else:
                labels.append(element)
        return labels

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.text.encode()).hexdigest()


_TABLE_KEYS = {
    "plan": ({"name"}, set()),
    "control": ({"id"}, {"description"}),
    "target": ({"id", "nominal", "search_radius"}, {"description"}),
    "reference_point": ({"id"}, {"description"}),
    "reference_line": ({"id", "probes"}, {"fit", "description"}),
    "characteristic": ({"name", "kind", "a", "nominal"}, {"b", "description", "tolerance", "upper_tol", "lower_tol"}),
    "uncertainty": (set(), {
        "coverage_factor", "decision_rule", "calibration_scale_u", "target_radius", "max_tilt_deg",
        "eccentricity_corrected", "eccentricity_residual", "consistency_alpha",
    }),
    "temperature": (set(), {
        "part", "u_part", "part_alpha", "u_part_alpha", "reference", "u_reference", "reference_alpha",
        "u_reference_alpha",
    }),
    "job": (set(), {"part", "serial", "operator", "order", "instrument"}),
    "instrument": ({"id"}, {"kind", "calibrated", "due"}),
}
_TOP_KEYS = (set(_TABLE_KEYS) - {"instrument"}) | {"probing_order"}


def _check_keys(entry: Any, table: str, where: str) -> dict[str, Any]:
    if not isinstance(entry, dict):
        raise ConfigError(f"{where}: expected a table, got {type(entry).__name__}")
    required, optional = _TABLE_KEYS[table]
    for key in entry:
        if key not in required | optional:
            raise ConfigError(
                f"{where}: unknown key {key!r}; allowed keys: {', '.join(sorted(required | optional))}"
            )
    for key in sorted(required):
        if key not in entry:
            raise ConfigError(f"{where}: missing key {key!r}")
    return entry


def _number(value: Any, where: str, key: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{where}: key {key!r} must be a number, got {value!r}")
    if positive and not value > 0:
        raise ConfigError(f"{where}: key {key!r} must be > 0, got {value!r}")
    return float(value)


def _text(value: Any, where: str, key: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{where}: key {key!r} must be a non-empty string, got {value!r}")
    if "." in value:
        raise ConfigError(f"{where}: key {key!r}: ids may not contain '.', got {value!r}")
    return value


def parse_plan(text: str, source: str = "<plan>") -> MeasurementPlan:
    """Parse and validate a plan; errors name ``source`` and the bad key."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None
    for key in data:
        if key not in _TOP_KEYS:
            raise ConfigError(f"{source}: unknown key {key!r}; allowed: {', '.join(sorted(_TOP_KEYS))}")

    def entries(table: str) -> list[dict[str, Any]]:
        value = data.get(table, [])
        if not isinstance(value, list):
            raise ConfigError(f"{source}: [[{table}]] must be an array of tables")
        return [_check_keys(e, table, f"{source}: [[{table}]] #{i + 1}") for i, e in enumerate(value)]

    head = _check_keys(data.get("plan", {"name": Path(source).stem}), "plan", f"{source}: [plan]")
    seen: dict[str, str] = {}

    def new_id(value: Any, where: str, key: str = "id") -> str:
        ident = _text(value, where, key)
        if ident in seen:
            raise ConfigError(f"{where}: duplicate id {ident!r} (already used by {seen[ident]})")
        seen[ident] = where
        return ident

    controls = tuple(
        new_id(e["id"], f"{source}: [[control]] #{i + 1}") for i, e in enumerate(entries("control"))
    )
    targets = []
    for i, e in enumerate(entries("target")):
        where = f"{source}: [[target]] #{i + 1}"
        nominal = e["nominal"]
        if not (isinstance(nominal, list) and len(nominal) == 3):
            raise ConfigError(f"{where}: key 'nominal' must be [x, y, z] in mm, got {nominal!r}")
        targets.append(
            TargetSpec(
                new_id(e["id"], where),
                np.array([_number(v, where, "nominal") for v in nominal]),
                _number(e["search_radius"], where, "search_radius", positive=True),
            )
        )
    ref_points = tuple(
        new_id(e["id"], f"{source}: [[reference_point]] #{i + 1}")
        for i, e in enumerate(entries("reference_point"))
    )
    lines = []
    for i, e in enumerate(entries("reference_line")):
        where = f"{source}: [[reference_line]] #{i + 1}"
        fit = e.get("fit", "line")
        if fit not in LINE_FITS:
            raise ConfigError(f"{where}: key 'fit' must be one of {LINE_FITS}, got {fit!r}")
        probes = e["probes"]
        minimum = 5 if fit == "cylinder" else 2
        if isinstance(probes, bool) or not isinstance(probes, int) or probes < minimum:
            raise ConfigError(f"{where}: key 'probes' must be an integer >= {minimum} for fit={fit!r}")
        lines.append(ReferenceLineSpec(new_id(e["id"], where), probes, fit))
    line_ids = {line.id for line in lines}
    point_ids = set(controls) | set(ref_points) | {t.id for t in targets}

    characteristics = []
    names: set[str] = set()
    for i, e in enumerate(entries("characteristic")):
        where = f"{source}: [[characteristic]] #{i + 1}"
        name = e["name"]
        if not isinstance(name, str) or name in names:
            raise ConfigError(f"{where}: key 'name' must be a unique string, got {name!r}")
        names.add(name)
        kind = e["kind"]
        if kind not in KINDS:
            raise ConfigError(f"{where}: key 'kind' must be one of {KINDS}, got {kind!r}")
        a, b = e["a"], e.get("b")
        if a not in point_ids:
            raise ConfigError(f"{where}: key 'a' names {a!r}, which is no point of this plan")
        if kind == "point_point" and b not in point_ids:
            raise ConfigError(f"{where}: key 'b' names {b!r}, which is no point of this plan")
        if kind == "point_line" and b not in line_ids:
            raise ConfigError(f"{where}: key 'b' names {b!r}, which is no reference line of this plan")
        if kind == "depth" and b is not None:
            raise ConfigError(f"{where}: key 'b' is not used by kind 'depth'")
        tolerance = None if "tolerance" not in e else _number(e["tolerance"], where, "tolerance", positive=True)
        upper = None if "upper_tol" not in e else _number(e["upper_tol"], where, "upper_tol")
        lower = None if "lower_tol" not in e else _number(e["lower_tol"], where, "lower_tol")
        if tolerance is None and (upper is None or lower is None):
            raise ConfigError(f"{where}: give key 'tolerance' (symmetric) or both 'upper_tol' and 'lower_tol'")
        upper = tolerance if upper is None else upper
        lower = tolerance if lower is None else lower
        if not upper + lower > 0:
            raise ConfigError(
                f"{where}: the zone [nominal - lower_tol, nominal + upper_tol] is empty "
                f"(upper_tol {upper!r}, lower_tol {lower!r})"
            )
        characteristics.append(
            CharacteristicSpec(
                name,
                kind,
                a,
                b,
                _number(e["nominal"], where, "nominal"),
                tolerance if tolerance is not None else max(upper, lower),
                upper,
                lower,
            )
        )

    probed = list(controls) + list(ref_points) + [line.id for line in lines]
    order = data.get("probing_order", probed)
    if not isinstance(order, list) or sorted(order) != sorted(probed):
        raise ConfigError(
            f"{source}: key 'probing_order' must list each control, reference point and "
            f"reference line exactly once ({', '.join(probed)}), got {order!r}"
        )
    if len(controls) < 3:
        raise ConfigError(f"{source}: [[control]] needs at least 3 control points, got {len(controls)}")
    return MeasurementPlan(
        uncertainty=_uncertainty(data.get("uncertainty", {}), source),
        temperature=_temperature(data.get("temperature", {}), source),
        job=_job(data.get("job", {}), source),
        name=str(head.get("name", Path(source).stem)),
        control_ids=controls,
        targets=tuple(targets),
        reference_point_ids=ref_points,
        reference_lines=tuple(lines),
        characteristics=tuple(characteristics),
        order=tuple(order),
        source=source,
        text=text,
    )


def _uncertainty(entry: Any, source: str) -> UncertaintySpec:
    where = f"{source}: [uncertainty]"
    e = _check_keys(entry, "uncertainty", where)
    spec = UncertaintySpec()
    rule = e.get("decision_rule", spec.decision_rule)
    if rule not in RULES:
        raise ConfigError(f"{where}: key 'decision_rule' must be one of {', '.join(RULES)}, got {rule!r}")
    corrected = e.get("eccentricity_corrected", False)
    if not isinstance(corrected, bool):
        raise ConfigError(f"{where}: key 'eccentricity_corrected' must be true or false, got {corrected!r}")
    alpha = _number(e.get("consistency_alpha", spec.consistency_alpha), where, "consistency_alpha", True)
    if not alpha < 1:
        raise ConfigError(f"{where}: key 'consistency_alpha' must be in (0, 1), got {alpha!r}")
    cal = e.get("calibration_scale_u")
    return UncertaintySpec(
        coverage_factor=_number(e.get("coverage_factor", 2.0), where, "coverage_factor", positive=True),
        decision_rule=rule,
        calibration_scale_u=None if cal is None else _non_negative(cal, where, "calibration_scale_u"),
        target_radius_mm=_non_negative(e.get("target_radius", 0.0), where, "target_radius"),
        max_tilt_deg=_non_negative(e.get("max_tilt_deg", 0.0), where, "max_tilt_deg"),
        eccentricity_corrected=corrected,
        eccentricity_residual=_non_negative(e.get("eccentricity_residual", 0.1), where, "eccentricity_residual"),
        consistency_alpha=alpha,
    )


def _non_negative(value: Any, where: str, key: str) -> float:
    number = _number(value, where, key)
    if number < 0:
        raise ConfigError(f"{where}: key {key!r} must be >= 0, got {value!r}")
    return number


def _temperature(entry: Any, source: str) -> Temperature:
    where = f"{source}: [temperature]"
    e = _check_keys(entry, "temperature", where)
    if not e:
        return Temperature()
    d = Temperature()
    return Temperature(
        part_c=_number(e.get("part", d.part_c), where, "part"),
        u_part_k=_non_negative(e.get("u_part", d.u_part_k), where, "u_part"),
        part_alpha_per_k=_non_negative(e.get("part_alpha", d.part_alpha_per_k), where, "part_alpha"),
        u_part_alpha_per_k=_non_negative(e.get("u_part_alpha", d.u_part_alpha_per_k), where, "u_part_alpha"),
        reference_c=_number(e.get("reference", d.reference_c), where, "reference"),
        u_reference_k=_non_negative(e.get("u_reference", d.u_reference_k), where, "u_reference"),
        reference_alpha_per_k=_non_negative(
            e.get("reference_alpha", d.reference_alpha_per_k), where, "reference_alpha"
        ),
        u_reference_alpha_per_k=_non_negative(
            e.get("u_reference_alpha", d.u_reference_alpha_per_k), where, "u_reference_alpha"
        ),
        stated=True,
    )


def _string(value: Any, where: str, key: str) -> str:
    if not isinstance(value, str):
        raise ConfigError(f"{where}: key {key!r} must be a string, got {value!r}")
    return value


def _job(entry: Any, source: str) -> JobHeader:
    where = f"{source}: [job]"
    e = _check_keys(entry, "job", where)
    instruments = e.get("instrument", [])
    if not isinstance(instruments, list):
        raise ConfigError(f"{where}: [[job.instrument]] must be an array of tables")
    items = []
    for i, entry_i in enumerate(instruments):
        w = f"{source}: [[job.instrument]] #{i + 1}"
        x = _check_keys(entry_i, "instrument", w)
        items.append(Instrument(*(_string(x.get(k, ""), w, k) for k in ("id", "kind", "calibrated", "due"))))
    return JobHeader(
        *(_string(e.get(k, ""), where, k) for k in ("part", "serial", "operator", "order")),
        instruments=tuple(items),
    )


def load_plan(path: str | Path) -> MeasurementPlan:
    """Read a plan file; errors name the file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read plan: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a plan: a binary file, not UTF-8 TOML text") from None
    return parse_plan(text, str(path))
