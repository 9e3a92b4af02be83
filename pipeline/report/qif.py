"""A session's results as a QIF 3.0.0 document (ISO 23952), validated against the official schema.

``crossfield export SESSION --qif FILE.qif`` (docs/qif.md). What the document holds, in the
schema's order (element names of QIFDocument.xsd and the schemas it includes):

- ``QPId``: the document's UUID; ``Header``: the application (crossfield) and a description;
  ``SoftwareDefinitions``: crossfield, Python and every stage plugin with its version;
  ``FileUnits``: millimetre and radian (every length below is in mm).
- ``CoordinateSystems``: the global (CMM) frame every coordinate refers to.
- ``MeasurementResources``: the stereo station as a ``LightPenCMM`` (QIF's optical CMM
  with CCD cameras) and the ROMER arm as an ``AACMM`` (articulated arm CMM), with the
  job's instruments (serial number, calibration dates) where their kind names one of them;
  any other instrument of the job as a ``ManualMeasurementDevice``.
- ``Features``: definitions, nominals and items of the plan's targets (nominal location);
  their measurements (and those of the probed controls, reference points and fitted
  reference lines / cylinders, which have no nominal in the plan) in ``Results``.
- ``Characteristics``: point_point and point_line as ``DistanceBetweenCharacteristic``
  (three-dimensional), depth (global Z of a point) as ``LinearCoordinateCharacteristic``
  (ZAXIS of the global frame); nominal ``TargetValue`` and the tolerance zone
  ``[-lower_tol, +upper_tol]`` about it (``DefinedAsLimit`` false).
- ``Results/MeasurementResultsSet/MeasurementResults``: the inspection traceability (order,
  operator, start, software), the part's serial number, the feature measurements, and per
  characteristic its ``Value`` with ``combinedUncertainty`` = u (the combined standard
  uncertainty, GUM 5.1.2), its ``Status`` (ISO 14253-1 decision: conforms -> PASS,
  does_not_conform -> FAIL, not_proven -> INDETERMINATE; measured in no frame ->
  NOT_ANALYZED) and, as QIF has no element for them, the expanded uncertainty U, the
  coverage factor k, the decision and its rule as ``Attributes``
  (``crossfield:U_mm``, ``crossfield:k``, ``crossfield:decision``, ``crossfield:decision_rule``).

QPIds: the document's and the results instance's are UUID-5 of the session (id and start
time: a re-export gives the same document); the characteristic items', characteristic
nominals' and feature items' are UUID-5 of the plan's name and the element's name, so
results of repeated sessions of one plan join in a QMS. Decimal values are written in
positional notation (``xs:decimal`` has no exponent) from ``repr``, so they read back to
the same double as report.json's.
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Iterable, Mapping, Sequence
from decimal import Decimal
from pathlib import Path
from typing import Any

from lxml import etree

from crossfield.errors import ConfigError
from crossfield.report.qif_features import QifFeature, session_features
from crossfield.report.qif_schema import QIF_NAMESPACE, QIF_VERSION, validate_qif

__all__ = [
    "ATTR_DECISION",
    "ATTR_DECISION_RULE",
    "ATTR_K",
    "ATTR_U",
    "QPID_NAMESPACE",
    "STATUS_OF_DECISION",
    "build_qif",
    "characteristic_qpid",
    "feature_qpid",
    "qif_bytes",
    "write_qif",
]

#: Namespace of crossfield's UUID-5 QPIds (fixed: changing it breaks every QMS join).
QPID_NAMESPACE = uuid.UUID("8f0c6d1e-3a57-5b2e-9c41-6e2d7f1a0b93")

#: ISO 14253-1 decision (report.json) -> QIF ``CharacteristicStatusEnum``.
STATUS_OF_DECISION = {"conforms": "PASS", "does_not_conform": "FAIL", "not_proven": "INDETERMINATE"}

ATTR_U = "crossfield:U_mm"
ATTR_K = "crossfield:k"
ATTR_DECISION = "crossfield:decision"
ATTR_DECISION_RULE = "crossfield:decision_rule"

_DEVICE_STATION = "station"
_DEVICE_ARM = "arm"


def characteristic_qpid(plan_name: str, characteristic: str) -> str:
    """The stable QPId of a plan's characteristic (UUID-5 of the plan name and the characteristic name)."""
    return str(uuid.uuid5(QPID_NAMESPACE, f"plan\x00{plan_name}\x00characteristic\x00{characteristic}"))


def feature_qpid(plan_name: str, feature: str) -> str:
    """The stable QPId of a plan's feature (target) item."""
    return str(uuid.uuid5(QPID_NAMESPACE, f"plan\x00{plan_name}\x00feature\x00{feature}"))


def _dec(value: float) -> str:
    """``value`` as xs:decimal text: positional notation of its repr (reads back to the same double)."""
    return format(Decimal(repr(float(value))), "f")


def _xyz(v: Sequence[float]) -> str:
    return " ".join(repr(float(x)) for x in v)  # xs:double list (PointSimpleType)


class _Doc:
    """Element builder with QIF ids (``id`` attributes numbered from 1; ``idMax``)."""

    def __init__(self) -> None:
        self.last_id = 0

    def new_id(self) -> int:
        self.last_id += 1
        return self.last_id

    @staticmethod
    def el(parent: Any, tag: str, text: Any = None, **attrs: Any) -> Any:
        node = etree.SubElement(parent, f"{{{QIF_NAMESPACE}}}{tag}", {k: str(v) for k, v in attrs.items()})
        if text is not None:
            node.text = str(text)
        return node

    def ids(self, parent: Any, tag: str, ids: Sequence[int]) -> Any:
        node = self.el(parent, tag, n=len(ids))
        for i in ids:
            self.el(node, "Id", i)
        return node

    def attributes(self, parent: Any, items: Sequence[tuple[str, str, Any]]) -> None:
        node = self.el(parent, "Attributes", n=len(items))
        for kind, name, value in items:
            self.el(node, kind, name=name, value=value)


def _finite(value: Any) -> bool:
    """A number that is not NaN or infinite (report.json writes NaN as null)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _datetime(iso_utc: str | None) -> str | None:
    return iso_utc.replace("+00:00", "Z") if iso_utc else None


def _date_time(date: str) -> str | None:
    """A plan date (``YYYY-MM-DD``) as xs:dateTime (midnight UTC); other text: None."""
    date = (date or "").strip()
    if len(date) == 10 and date[4] == "-" and date[7] == "-" and date.replace("-", "").isdigit():
        return f"{date}T00:00:00Z"
    return None


def _header(d: _Doc, root: Any, report: Mapping[str, Any]) -> None:
    header = d.el(root, "Header")
    app = d.el(header, "Application")
    d.el(app, "Name", "crossfield")
    d.el(app, "Organization", "crossfield project")
    d.el(header, "Description", f"crossfield session {report['session']['id']}: cross-field lengths measured "
         f"by local stereo vision registered to out-of-view CMM references; plan {report['plan']['name']!r}")
    d.el(header, "Scope", "Results")


def _software(d: _Doc, root: Any, report: Mapping[str, Any]) -> list[int]:
    """crossfield, Python and every stage plugin with its version: their ids."""
    entries: list[tuple[str, str, str, str]] = []
    packages = report.get("packages") or {}
    entries.append(("crossfield project", "crossfield", str(packages.get("crossfield", "")), "the pipeline"))
    if packages.get("python"):
        entries.append(("Python Software Foundation", "Python", str(packages["python"]), "interpreter"))
    for stage, plugin in (report.get("plugins") or {}).items():
        entries.append((str(plugin.get("package") or "unknown"), f"{stage}-{plugin.get('name', '')}",
                        str(plugin.get("version") or ""), f"{stage} stage: {plugin.get('plugin', '')}"))
    software = d.el(root, "SoftwareDefinitions", n=len(entries))
    ids = []
    for vendor, name, version, description in entries:
        ids.append(d.new_id())
        node = d.el(software, "Software", id=ids[-1])
        d.el(node, "VendorName", vendor)
        d.el(node, "ApplicationName", name)
        if version:
            d.el(node, "Version", version)
        d.el(node, "Description", description)
    return ids


def _units(d: _Doc, root: Any) -> None:
    """mm and radian (QIF fixes ``SIUnitName`` to the SI unit; mm is 0.001 meter)."""
    units = d.el(d.el(root, "FileUnits"), "PrimaryUnits")
    angular = d.el(units, "AngularUnit")
    d.el(angular, "SIUnitName", "radian")
    d.el(angular, "UnitName", "radian")
    linear = d.el(units, "LinearUnit")
    d.el(linear, "SIUnitName", "meter")
    d.el(linear, "UnitName", "mm")
    d.el(d.el(linear, "UnitConversion"), "Factor", "0.001")


def _instrument_role(kind: str) -> str | None:
    kind = kind.lower()
    if "arm" in kind or "cmm" in kind or "romer" in kind:
        return _DEVICE_ARM
    if any(word in kind for word in ("camera", "stereo", "station", "vision")):
        return _DEVICE_STATION
    return None


def _device(d: _Doc, parent: Any, tag: str, name: str, description: str, *, model: str = "",
            instrument: Mapping[str, Any] | None = None) -> int:
    did = d.new_id()
    node = d.el(parent, tag, id=did)
    d.el(node, "Name", name)
    d.el(node, "Description", description)
    if model:
        d.el(node, "ModelNumber", model)
    if instrument:
        d.el(node, "SerialNumber", instrument.get("id", ""))
        due = _date_time(str(instrument.get("due") or ""))
        if due:
            calibrations = d.el(node, "Calibrations", n=1)
            calibration = d.el(calibrations, "Calibration")
            done = _date_time(str(instrument.get("calibrated") or ""))
            if done:
                d.el(calibration, "CalibrationDate", done)
            d.el(calibration, "ExpirationDate", due)
    return did


def _resources(d: _Doc, root: Any, report: Mapping[str, Any]) -> dict[str, int]:
    devices = d.el(d.el(root, "MeasurementResources"), "MeasurementDevices")
    instruments = list((report.get("job") or {}).get("instruments") or ())
    by_role: dict[str, Mapping[str, Any]] = {}
    others = []
    for instrument in instruments:
        role = _instrument_role(str(instrument.get("kind", "")))
        if role is not None and role not in by_role:
            by_role[role] = instrument
        else:
            others.append(instrument)
    acquisition = report.get("acquisition") or {}
    ids = {
        _DEVICE_STATION: _device(
            d, devices, "LightPenCMM", "stereo station",
            "short-baseline parallel-axis stereo camera pair (upper, lower) measuring circular targets; "
            f"acquisition: {acquisition.get('source', '')}", model=str(acquisition.get("camera_model") or ""),
            instrument=by_role.get(_DEVICE_STATION)),
        _DEVICE_ARM: _device(
            d, devices, "AACMM", "ROMER arm",
            f"portable articulated-arm CMM probing the controls and references; source: "
            f"{(report.get('reference') or {}).get('source', '')}", instrument=by_role.get(_DEVICE_ARM)),
    }
    for k, instrument in enumerate(others):
        ids[f"other{k}"] = _device(d, devices, "ManualMeasurementDevice", str(instrument.get("id") or "instrument"),
                                   str(instrument.get("kind") or ""), instrument=instrument)
    devices.set("n", str(len(ids)))
    return ids


def _features(d: _Doc, root: Any, features: Sequence[QifFeature], plan_name: str) -> dict[str, int]:
    """Definitions, nominals and items of the features with a nominal (the targets): id -> item id."""
    nominal = [f for f in features if f.nominal_mm is not None]
    if not nominal:
        return {}
    node = d.el(root, "Features")
    definitions = d.el(node, "FeatureDefinitions", n=len(nominal))
    definition_ids = {}
    for f in nominal:
        definition_ids[f.id] = d.new_id()
        d.el(definitions, "PointFeatureDefinition", id=definition_ids[f.id])
    nominals = d.el(node, "FeatureNominals", n=len(nominal))
    nominal_ids = {}
    for f in nominal:
        nominal_ids[f.id] = d.new_id()
        n = d.el(nominals, "PointFeatureNominal", id=nominal_ids[f.id])
        d.el(n, "FeatureDefinitionId", definition_ids[f.id])
        d.el(n, "Location", _xyz(f.nominal_mm))
    items = d.el(node, "FeatureItems", n=len(nominal))
    item_ids = {}
    for f in nominal:
        item_ids[f.id] = d.new_id()
        item = d.el(items, "PointFeatureItem", id=item_ids[f.id])
        d.el(item, "FeatureNominalId", nominal_ids[f.id])
        d.el(item, "FeatureName", f.id)
        d.el(item, "UUID", feature_qpid(plan_name, f.id))
        d.el(d.el(item, "DeterminationMode"), "Checked")
    return item_ids


_CHARACTERISTIC_TAG = {"point_point": "DistanceBetween", "point_line": "DistanceBetween", "depth": "LinearCoordinate"}


def _characteristic_tag(c: Mapping[str, Any]) -> str:
    kind = c.get("kind")
    if kind not in _CHARACTERISTIC_TAG:
        raise ConfigError(f"characteristic {c.get('name')!r}: kind {kind!r} has no QIF characteristic "
                          f"(known: {', '.join(_CHARACTERISTIC_TAG)})")
    return _CHARACTERISTIC_TAG[kind]


def _characteristics(d: _Doc, root: Any, report: Mapping[str, Any], item_of_feature: Mapping[str, int],
                     device_ids: Mapping[str, int], frame_id: int, standard_id: int) -> dict[str, int]:
    """Characteristic definitions, nominals and items: name -> item id."""
    chars = report["characteristics"]
    plan_name = report["plan"]["name"]
    node = d.el(root, "Characteristics")
    d.el(node, "FormalStandardId", standard_id)
    definitions = d.el(node, "CharacteristicDefinitions", n=len(chars))
    definition_ids = {}
    for c in chars:
        tag = _characteristic_tag(c)
        definition_ids[c["name"]] = d.new_id()
        defn = d.el(definitions, f"{tag}CharacteristicDefinition", id=definition_ids[c["name"]])
        tol = d.el(defn, "Tolerance")
        d.el(tol, "MaxValue", _dec(c["upper_tol_mm"]))
        d.el(tol, "MinValue", _dec(-c["lower_tol_mm"]))
        d.el(tol, "DefinedAsLimit", "false")
    nominals = d.el(node, "CharacteristicNominals", n=len(chars))
    nominal_ids = {}
    for c in chars:
        tag = _characteristic_tag(c)
        nominal_ids[c["name"]] = d.new_id()
        nom = d.el(nominals, f"{tag}CharacteristicNominal", id=nominal_ids[c["name"]])
        d.el(nom, "CharacteristicDefinitionId", definition_ids[c["name"]])
        d.el(nom, "Name", c["name"])
        d.el(nom, "TargetValue", _dec(c["nominal_mm"]))
        if tag == "DistanceBetween":
            d.el(nom, "AnalysisMode", "THREEDIMENSIONAL")
        else:
            d.el(nom, "Direction", "ZAXIS")
            d.el(nom, "CoordinateSystemId", frame_id)
    items = d.el(node, "CharacteristicItems", n=len(chars))
    item_ids = {}
    for c in chars:
        tag = _characteristic_tag(c)
        item_ids[c["name"]] = d.new_id()
        item = d.el(items, f"{tag}CharacteristicItem", id=item_ids[c["name"]])
        d.el(item, "Name", c["name"])
        designator = d.el(item, "CharacteristicDesignator")
        d.el(designator, "Designator", c["name"])
        d.el(designator, "UUID", characteristic_qpid(plan_name, c["name"]))
        feature_items = [item_of_feature[e] for e in c.get("elements", ()) if e in item_of_feature]
        if feature_items:
            d.ids(item, "FeatureItemIds", feature_items)
        d.ids(item, "MeasurementDeviceIds", [device_ids[_DEVICE_STATION], device_ids[_DEVICE_ARM]])
        d.el(item, "CharacteristicNominalId", nominal_ids[c["name"]])
    return item_ids


def _standards(d: _Doc, root: Any) -> int:
    """ISO 14253-1, the standard of the decisions: its id."""
    standards = d.el(root, "StandardsDefinitions", n=1)
    sid = d.new_id()
    standard = d.el(standards, "Standard", id=sid)
    d.el(d.el(standard, "Organization"), "StandardsOrganizationEnum", "ISO")
    d.el(standard, "Designator", "14253-1")
    d.el(standard, "Title", "Decision rules for verifying conformity or nonconformity with specifications")
    return sid


def _coordinate_systems(d: _Doc, root: Any) -> int:
    systems = d.el(root, "CoordinateSystems")
    definitions = d.el(systems, "CoordinateSystemDefinitions", n=1)
    cid = d.new_id()
    system = d.el(definitions, "CoordinateSystem", id=cid)
    d.el(system, "Name", "global (CMM reference frame)")
    return cid


def _feature_measurements(d: _Doc, parent: Any, features: Sequence[QifFeature], item_of_feature: Mapping[str, int],
                          device_ids: Mapping[str, int]) -> dict[str, int]:
    node = d.el(parent, "MeasuredFeatures", n=len(features))
    ids = {}
    for f in features:
        ids[f.id] = d.new_id()
        tag = {"point": "PointFeatureMeasurement", "line": "LineFeatureMeasurement",
               "cylinder": "CylinderFeatureMeasurement"}[f.kind]
        m = d.el(node, tag, id=ids[f.id])
        d.attributes(m, [("AttributeStr", "crossfield:role", f.role), ("AttributeI1", "crossfield:n", f.n)])
        if f.id in item_of_feature:
            d.el(m, "FeatureItemId", item_of_feature[f.id])
        d.el(m, "FeatureName", f.id)
        device = device_ids[_DEVICE_STATION if f.role == "target" else _DEVICE_ARM]
        d.ids(m, "MeasurementDeviceIds", [device])
        if f.kind == "point":
            d.el(m, "Location", _xyz(f.location_mm))
        elif f.kind == "line":
            d.el(m, "Location", _xyz(f.location_mm))
            d.el(m, "Direction", _xyz(f.direction))
            if f.form_mm is not None:
                d.el(m, "Form", _dec(f.form_mm))
        else:
            axis = d.el(m, "Axis")
            d.el(axis, "AxisPoint", _xyz(f.location_mm))
            d.el(axis, "Direction", _xyz(f.direction))
            if f.diameter_mm is not None:
                d.el(m, "Diameter", _dec(f.diameter_mm))
            if f.form_mm is not None:
                d.el(m, "Form", _dec(f.form_mm))
    return ids


def _results(d: _Doc, root: Any, report: Mapping[str, Any], features: Sequence[QifFeature],
             item_of_feature: Mapping[str, int], item_of_characteristic: Mapping[str, int],
             device_ids: Mapping[str, int], software_ids: Sequence[int], results_qpid: str) -> None:
    results = d.el(root, "Results")
    result_set = d.el(results, "MeasurementResultsSet", n=1)
    mr = d.el(result_set, "MeasurementResults", id=d.new_id())
    job = report.get("job") or {}
    session = report["session"]
    trace = d.el(mr, "InspectionTraceability")
    if job.get("order"):
        d.el(trace, "OrderNumber", job["order"])
    d.el(trace, "ReportNumber", session["id"])
    start = _datetime(session.get("start_time_utc"))
    if start:
        d.el(trace, "InspectionStart", start)
    d.ids(d.el(trace, "InspectionSoftwareItems"), "InspectionProgramExecutionSoftware", list(software_ids))
    if job.get("operator"):
        d.el(d.el(trace, "InspectionOperator"), "Name", job["operator"])
    d.el(mr, "ThisResultsInstanceQPId", results_qpid)
    feature_ids = _feature_measurements(d, mr, features, item_of_feature, device_ids) if features else {}
    chars = report["characteristics"]
    measured = d.el(d.el(mr, "MeasuredCharacteristics"), "CharacteristicMeasurements", n=len(chars)) \
        if chars else None  # none evaluated: the schema wants at least one, so no element
    for c in chars:
        tag = _characteristic_tag(c)
        m = d.el(measured, f"{tag}CharacteristicMeasurement", id=d.new_id())
        value = c.get("measured_mm")
        attrs: list[tuple[str, str, Any]] = []
        if _finite(c.get("expanded_uncertainty_mm")):
            attrs.append(("AttributeD1", ATTR_U, repr(float(c["expanded_uncertainty_mm"]))))
        if _finite(c.get("coverage_factor")):
            attrs.append(("AttributeD1", ATTR_K, repr(float(c["coverage_factor"]))))
        attrs.append(("AttributeStr", ATTR_DECISION, str(c.get("decision"))))
        attrs.append(("AttributeStr", ATTR_DECISION_RULE, str(c.get("decision_rule"))))
        d.attributes(m, attrs)
        status = "NOT_ANALYZED" if not _finite(value) else STATUS_OF_DECISION.get(str(c.get("decision")), "UNDEFINED")
        d.el(d.el(m, "Status"), "CharacteristicStatusEnum", status)
        d.el(m, "CharacteristicItemId", item_of_characteristic[c["name"]])
        feature_measurements = [feature_ids[e] for e in c.get("elements", ()) if e in feature_ids]
        if feature_measurements:
            d.ids(m, "FeatureMeasurementIds", feature_measurements)
        d.ids(m, "MeasurementDeviceIds", [device_ids[_DEVICE_STATION], device_ids[_DEVICE_ARM]])
        if tag == "LinearCoordinate":
            d.el(d.el(m, "TypeOfCoordinates"), "CoordinateEnum", "CARTESIAN_3D")
        if _finite(value):
            node = d.el(m, "Value", _dec(value))
            if _finite(c.get("uncertainty_mm")):
                node.set("combinedUncertainty", _dec(c["uncertainty_mm"]))
    if report.get("incomplete"):
        inspection = "NOT_CALCULATED"
    else:
        inspection = "PASS" if report.get("passed") else "FAIL"
    d.el(d.el(mr, "InspectionStatus"), "InspectionStatusEnum", inspection)
    if job.get("serial") or job.get("part"):
        sets = d.el(results, "ActualComponentSets", n=1)
        component_set = d.el(sets, "ActualComponentSet", n=1)
        component = d.el(component_set, "ActualComponent", id=d.new_id())
        if job.get("part"):
            d.attributes(component, [("AttributeStr", "crossfield:part", job["part"])])
        if job.get("serial"):
            d.el(component, "SerialNumber", job["serial"])
        d.el(d.el(component, "Status"), "InspectionStatusEnum", inspection)


def build_qif(report: Mapping[str, Any], features: Iterable[QifFeature] = ()) -> etree._ElementTree:
    """The QIF 3.0.0 document of a report.json document and the session's measured features
    (:mod:`crossfield.report.qif_features`; none: no feature section). Not validated here:
    :func:`qif_bytes` and :func:`write_qif` validate."""
    features = tuple(features)
    session = report["session"]
    seed = f"{session['id']}\x00{session.get('start_time_ns', 0)}"
    d = _Doc()
    root = etree.Element(f"{{{QIF_NAMESPACE}}}QIFDocument", nsmap={None: QIF_NAMESPACE},
                         versionQIF=QIF_VERSION)
    d.el(root, "QPId", uuid.uuid5(QPID_NAMESPACE, f"document\x00{seed}"))
    _header(d, root, report)
    standard_id = _standards(d, root)
    software_ids = _software(d, root, report)
    _units(d, root)
    frame_id = _coordinate_systems(d, root)
    device_ids = _resources(d, root, report)
    plan_name = report["plan"]["name"]
    item_of_feature = _features(d, root, features, plan_name)
    item_of_characteristic = _characteristics(d, root, report, item_of_feature, device_ids, frame_id, standard_id) \
        if report["characteristics"] else {}
    _results(d, root, report, features, item_of_feature, item_of_characteristic, device_ids, software_ids,
             str(uuid.uuid5(QPID_NAMESPACE, f"results\x00{seed}")))
    root.set("idMax", str(d.last_id))
    return etree.ElementTree(root)


def qif_bytes(report: Mapping[str, Any], features: Iterable[QifFeature] = ()) -> bytes:
    """The validated QIF document (UTF-8 XML with declaration); raises
    :class:`~crossfield.report.qif_schema.QifValidationError` if it does not follow the schema."""
    data = etree.tostring(build_qif(report, features), xml_declaration=True, encoding="UTF-8", pretty_print=True)
    validate_qif(data, f"QIF document of session {report['session']['id']}")  # from the text: line numbers
    return data


def write_qif(session: str | Path, path: str | Path) -> Path:
    """Write the validated QIF document of ``session`` (a session folder or its report.json;
    features from the folder's session.mcap when there is one) to ``path``."""
    from crossfield.export import load_report

    report = load_report(session)
    folder = Path(session)
    if not folder.is_dir():
        folder = folder.parent
    data = qif_bytes(report, session_features(folder, report))
    path = Path(path)
    try:
        path.write_bytes(data)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write the QIF file: {exc.strerror}") from None
    return path
