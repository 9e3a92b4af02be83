"""crossfield export SESSION --qif FILE: QIF 3.0.0 documents validated against the official schema.

Every simulator scenario's document validates (the official XSD, lxml); its values read back
(parsed with lxml, not with crossfield) equal report.json's bit for bit; features sit on the
simulator's truth; QPIds of a plan's characteristics are the same in repeated sessions; a
broken document fails with one clear line naming file, line and schema message.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from lxml import etree

from crossfield.cli import main
from crossfield.recording.facts import load_session_facts
from crossfield.report import qif
from crossfield.report.qif_schema import QIF_NAMESPACE, QifValidationError, validate_qif
from crossfield.simulator.scenarios import CYLINDER_RADIUS_MM, SCENARIOS, build_scene

from session_tools import record_session

NS = {"q": QIF_NAMESPACE}

#: The station plan with a job header, a guarded-acceptance rule and nominals that give
#: each ISO 14253-1 decision (P1-P2 outside its zone; P1-depth within U of its limit).
JOB_TOML = """
[uncertainty]
decision_rule = "guarded_acceptance"

[job]
part = "Housing 42"
serial = "SN-0815"
operator = "A. Smith"
order = "WO-2026-117"

[[job.instrument]]
id = "ROMER-7525"
kind = "CMM arm"
calibrated = "2026-03-02"
due = "2027-03-02"

[[job.instrument]]
id = "STEREO-1"
kind = "stereo camera station"
calibrated = "2026-05-01"
due = "2027-11-01"

[[job.instrument]]
id = "TH-3"
kind = "thermometer"
due = "2027-01-15"
"""


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """One recorded 1-frame session per scenario, and a station session with the job plan."""
    out = tmp_path_factory.mktemp("qif")
    folders = {}
    for scenario in SCENARIOS:
        record_session(out, scenario, scenario=scenario, frames=1, seed=4, report={"plugin": "json"})
        folders[scenario] = out / scenario
    text = build_scene("station").plan.text
    text = text.replace("nominal = 54.8\n", "nominal = 55.2\n").replace("nominal = 670.1\n", "nominal = 669.9105\n")
    plan = out / "job_plan.toml"
    plan.write_text(text + JOB_TOML, encoding="utf-8")
    record_session(out, "job", scenario="station", frames=1, seed=4, session={"plan": str(plan)},
                   report={"plugin": "json"})
    folders["job"] = out / "job"
    return folders


def export(folder, tmp_path, name):
    path = tmp_path / f"{name}.qif"
    assert main(["export", str(folder), "--qif", str(path)]) == 0
    return path


def by_id(root):
    return {int(e.get("id")): e for e in root.iter() if e.get("id") is not None}


def local(element):
    return etree.QName(element).localname


def attributes(element):
    return {a.get("name"): a.get("value") for a in element.findall("q:Attributes/*", NS)}


def read_characteristics(root):
    """name -> what the QIF document says of it, read with lxml only."""
    ids = by_id(root)
    out = {}
    for m in root.findall("q:Results/q:MeasurementResultsSet/q:MeasurementResults/q:MeasuredCharacteristics/"
                          "q:CharacteristicMeasurements/*", NS):
        item = ids[int(m.findtext("q:CharacteristicItemId", namespaces=NS))]
        nominal = ids[int(item.findtext("q:CharacteristicNominalId", namespaces=NS))]
        definition = ids[int(nominal.findtext("q:CharacteristicDefinitionId", namespaces=NS))]
        value = m.find("q:Value", NS)
        attrs = attributes(m)
        out[item.findtext("q:Name", namespaces=NS)] = {
            "tag": local(m),
            "measured": None if value is None else float(value.text),
            "u": None if value is None else float(value.get("combinedUncertainty")),
            "U": float(attrs[qif.ATTR_U]),
            "k": float(attrs[qif.ATTR_K]),
            "decision": attrs[qif.ATTR_DECISION],
            "rule": attrs[qif.ATTR_DECISION_RULE],
            "status": m.findtext("q:Status/q:CharacteristicStatusEnum", namespaces=NS),
            "nominal": float(nominal.findtext("q:TargetValue", namespaces=NS)),
            "upper": float(definition.findtext("q:Tolerance/q:MaxValue", namespaces=NS)),
            "lower": -float(definition.findtext("q:Tolerance/q:MinValue", namespaces=NS)),
            "qpid": item.findtext("q:CharacteristicDesignator/q:UUID", namespaces=NS),
            "features": [ids[int(i.text)].findtext("q:FeatureName", namespaces=NS)
                         for i in m.findall("q:FeatureMeasurementIds/q:Id", NS)],
        }
    return out


@pytest.mark.parametrize("scenario", [*SCENARIOS, "job"])
def test_every_scenario_validates_and_round_trips(sessions, tmp_path, scenario):
    folder = sessions[scenario]
    path = export(folder, tmp_path, scenario)
    validate_qif(path)  # the official QIF 3.0.0 schema (lxml), independently of the export's own check
    report = json.loads((folder / "report.json").read_text(encoding="utf-8"))
    root = etree.parse(str(path)).getroot()
    assert root.get("versionQIF") == "3.0.0"
    assert int(root.get("idMax")) == max(by_id(root))
    assert root.findtext("q:FileUnits/q:PrimaryUnits/q:LinearUnit/q:UnitName", namespaces=NS) == "mm"
    read = read_characteristics(root)
    assert list(read) == [c["name"] for c in report["characteristics"]]
    for c in report["characteristics"]:
        q = read[c["name"]]
        assert q["measured"] == c["measured_mm"]  # bit for bit: decimals written from repr
        assert q["u"] == c["uncertainty_mm"]
        assert q["U"] == c["expanded_uncertainty_mm"] and q["k"] == c["coverage_factor"]
        assert q["decision"] == c["decision"] and q["rule"] == c["decision_rule"]
        assert q["status"] == qif.STATUS_OF_DECISION[c["decision"]]
        assert (q["nominal"], q["upper"], q["lower"]) == (c["nominal_mm"], c["upper_tol_mm"], c["lower_tol_mm"])
        assert q["tag"] == ("LinearCoordinateCharacteristicMeasurement" if c["kind"] == "depth"
                            else "DistanceBetweenCharacteristicMeasurement")
        assert q["features"] == c["elements"]  # every element measured: targets, CMM points, lines
    status = root.findtext("q:Results//q:InspectionStatus/q:InspectionStatusEnum", namespaces=NS)
    assert status == ("PASS" if report["passed"] else "FAIL")


def test_features_sit_on_the_simulator_truth(sessions, tmp_path):
    """Targets (camera, mean of 2 frames) within 0.05 mm of truth, the cylinder's diameter and the
    depth characteristic consistent with the feature it is made of."""
    path = export(sessions["station"], tmp_path, "station")
    root = etree.parse(str(path)).getroot()
    scene = build_scene("station")
    report = json.loads((sessions["station"] / "report.json").read_text(encoding="utf-8"))
    features = {m.findtext("q:FeatureName", namespaces=NS): m
                for m in root.findall("q:Results//q:MeasuredFeatures/*", NS)}
    assert {"P1", "P2", "R1", "L3", *(f"C{k}" for k in range(1, 9))} <= set(features)
    p1 = np.array(features["P1"].findtext("q:Location", namespaces=NS).split(), dtype=float)
    depth = next(c for c in report["characteristics"] if c["name"] == "P1-depth")
    assert p1[2] == pytest.approx(depth["measured_mm"], abs=1e-9)  # depth = global Z of the mean point
    truth_points = load_session_facts(sessions["station"] / "session.mcap").ground_truth.points_global
    for name in ("P1", "P2", "R1", "C1"):
        xyz = np.array(features[name].findtext("q:Location", namespaces=NS).split(), dtype=float)
        assert np.linalg.norm(xyz - truth_points[name]) < 0.05, name
    cylinder = features["L3"]
    assert local(cylinder) == "CylinderFeatureMeasurement"
    assert float(cylinder.findtext("q:Diameter", namespaces=NS)) == pytest.approx(2 * CYLINDER_RADIUS_MM, abs=0.05)
    # the nominal side: the plan's targets, with the plan's nominal
    nominal = root.find("q:Features/q:FeatureNominals/q:PointFeatureNominal", NS)
    spec = scene.plan.targets[0]
    assert np.array(nominal.findtext("q:Location", namespaces=NS).split(), dtype=float) == pytest.approx(spec.nominal)


def test_job_header_instruments_and_every_decision(sessions, tmp_path):
    path = export(sessions["job"], tmp_path, "job")
    root = etree.parse(str(path)).getroot()
    read = read_characteristics(root)
    assert read["P1-P2"]["decision"] == "does_not_conform" and read["P1-P2"]["status"] == "FAIL"
    assert read["P1-depth"]["decision"] == "not_proven" and read["P1-depth"]["status"] == "INDETERMINATE"
    assert read["P1-L3"]["status"] == "PASS"
    devices = root.find("q:MeasurementResources/q:MeasurementDevices", NS)
    kinds = {local(d): d for d in devices}
    assert set(kinds) == {"LightPenCMM", "AACMM", "ManualMeasurementDevice"}
    assert kinds["AACMM"].findtext("q:SerialNumber", namespaces=NS) == "ROMER-7525"
    assert kinds["AACMM"].findtext("q:Calibrations/q:Calibration/q:ExpirationDate", namespaces=NS) == \
        "2027-03-02T00:00:00Z"
    assert kinds["LightPenCMM"].findtext("q:SerialNumber", namespaces=NS) == "STEREO-1"
    trace = root.find("q:Results//q:InspectionTraceability", NS)
    assert trace.findtext("q:OrderNumber", namespaces=NS) == "WO-2026-117"
    assert trace.findtext("q:InspectionOperator/q:Name", namespaces=NS) == "A. Smith"
    assert root.findtext("q:Results/q:ActualComponentSets//q:SerialNumber", namespaces=NS) == "SN-0815"
    software = {s.findtext("q:ApplicationName", namespaces=NS): s.findtext("q:Version", namespaces=NS)
                for s in root.findall("q:SoftwareDefinitions/q:Software", NS)}
    assert software["crossfield"] and "centroid-modelfit" in software


def test_characteristic_qpids_are_stable_across_sessions(sessions, tmp_path):
    """Two sessions of one plan: the same characteristic and feature item QPIds, other document QPIds."""
    again = record_session(tmp_path, "again", scenario="station", frames=1, seed=9, report={"plugin": "json"})
    assert again.characteristics
    first = etree.parse(str(export(sessions["station"], tmp_path, "a"))).getroot()
    second = etree.parse(str(export(tmp_path / "again", tmp_path, "b"))).getroot()
    qpids_1 = {k: v["qpid"] for k, v in read_characteristics(first).items()}
    qpids_2 = {k: v["qpid"] for k, v in read_characteristics(second).items()}
    assert qpids_1 == qpids_2 and len(set(qpids_1.values())) == len(qpids_1)
    assert qpids_1["P1-L3"] == qif.characteristic_qpid("simulator station", "P1-L3")
    items = ".//q:FeatureItems/q:PointFeatureItem/q:UUID"
    assert [u.text for u in first.findall(items, NS)] == [u.text for u in second.findall(items, NS)]
    assert first.findtext("q:QPId", namespaces=NS) != second.findtext("q:QPId", namespaces=NS)
    # a re-export of one session is the same document
    assert export(sessions["station"], tmp_path, "c").read_bytes() == (tmp_path / "a.qif").read_bytes()


def test_broken_documents_fail_with_a_clear_message(sessions, tmp_path):
    good = export(sessions["table3"], tmp_path, "good").read_text(encoding="utf-8")
    cases = {
        # a measured value that is not a decimal
        "value": (re.sub(r"(<Value combinedUncertainty=\"[^\"]*\">)[^<]*", r"\1three hundred", good, count=1),
                  r"Value.*not a valid value of the atomic type 'xs:decimal'"),
        # a required element gone: the results' InspectionStatus
        "status": (re.sub(r"\s*<InspectionStatus>.*?</InspectionStatus>", "", good, count=1, flags=re.DOTALL),
                   r"Missing child element\(s\)|not expected"),
        # a characteristic measurement pointing at an item that does not exist (QIF id key/keyref)
        "reference": (re.sub(r"<CharacteristicItemId>\d+<", "<CharacteristicItemId>99999<", good, count=1),
                      r"No match found for key-sequence \['99999'\]"),
    }
    for name, (text, pattern) in cases.items():
        assert text != good, name
        path = tmp_path / f"broken-{name}.qif"
        path.write_text(text, encoding="utf-8")
        with pytest.raises(QifValidationError) as err:
            validate_qif(path)
        message = str(err.value)
        assert "\n" not in message
        assert re.match(rf"{re.escape(str(path))}:\d+: QIF 3\.0\.0 schema: ", message), message
        assert re.search(pattern, message), message
    (tmp_path / "cut.qif").write_text(good[: len(good) // 2], encoding="utf-8")
    with pytest.raises(QifValidationError, match=r"cut\.qif: not well-formed XML"):
        validate_qif(tmp_path / "cut.qif")


def test_export_needs_a_format_and_reports_bad_input(tmp_path, capsys):
    assert main(["export", str(tmp_path)]) == 2
    assert "give --csv FILE and/or --qif FILE" in capsys.readouterr().err
    assert main(["export", str(tmp_path), "--qif", str(tmp_path / "x.qif")]) == 2
    assert "a folder without session.mcap or report.json; export wants a session folder" in capsys.readouterr().err


def test_a_report_without_recording_incomplete_and_unmeasured_still_validates(tmp_path, capsys):
    """report.json alone (no session.mcap): an incomplete session, a characteristic measured in no
    frame (NOT_ANALYZED, no Value) and markup in the texts give a valid document."""
    from crossfield.report.document import build_report, dumps

    from test_report import make_summary

    report = build_report(make_summary(incomplete="stopped by the operator"))
    report["characteristics"][0].update(measured_mm=None, uncertainty_mm=None, decision="not_proven")
    report["job"].update(part="<Housing & 42>", serial="SN-\"0815\"")
    (tmp_path / "report.json").write_text(dumps(report), encoding="utf-8")
    path = export(tmp_path, tmp_path, "alone")
    validate_qif(path)
    root = etree.parse(str(path)).getroot()
    first = root.find("q:Results//q:CharacteristicMeasurements/*", NS)
    assert first.findtext("q:Status/q:CharacteristicStatusEnum", namespaces=NS) == "NOT_ANALYZED"
    assert first.find("q:Value", NS) is None
    assert root.findtext("q:Results//q:InspectionStatus/q:InspectionStatusEnum", namespaces=NS) == "NOT_CALCULATED"
    assert root.findtext("q:Results/q:ActualComponentSets//q:SerialNumber", namespaces=NS) == 'SN-"0815"'
    read = read_characteristics(root)
    for c in report["characteristics"][1:]:
        assert read[c["name"]]["measured"] == c["measured_mm"] and read[c["name"]]["U"] == c["expanded_uncertainty_mm"]
    targets = {m.findtext("q:FeatureName", namespaces=NS) for m in root.findall("q:Results//q:MeasuredFeatures/*", NS)}
    listed = {t for f in report["frames"] for t in f["target_points_mm"]}
    assert targets == listed and listed  # the targets of the frames report.json lists
    report["characteristics"] = []  # no characteristic evaluated
    validate_qif(qif.qif_bytes(report))


def test_a_recording_of_another_session_is_refused(sessions, tmp_path, capsys):
    import shutil

    folder = tmp_path / "mixed"
    folder.mkdir()
    shutil.copy(sessions["table3"] / "report.json", folder / "report.json")
    shutil.copy(sessions["station"] / "session.mcap", folder / "session.mcap")
    assert main(["export", str(folder), "--qif", str(tmp_path / "x.qif")]) == 2
    assert "the recording of session 'station', not of the report's session 'table3'" in capsys.readouterr().err
    assert not (tmp_path / "x.qif").exists()
