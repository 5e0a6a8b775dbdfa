"""Sweeps on Dask: spec validation, case expansion, the table against cases run one by one,
a local cluster of 2 workers and the default engine, a killed sweep resumed, failures kept."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from tofhil.errors import TofhilError
from tofhil.app import sweep as S
from tofhil.app.sweep import run as sweep_run  # the module that holds the twin cache and its render count

#: 4 tiny cases (wall_card at 40 x 30): two card reflectances x two seeds, a weak stray light
#: in the measurement, compared with the twin that lacks it.
SPEC = {
    "name": "tiny",
    "scene": "wall_card",
    "frames": 2,
    "effects": {"stray_light": {"weight": 0.03, "sigma_px": 4.0}},
    "axes": {"camera.scale": [0.25], "params.card_reflectance": [0.4, 0.8], "seed": [0, 1]},
    "compare": {"reference": "twin", "frames": 2},
}


def spec_of(d: dict, tmp_path: Path | None = None) -> S.SweepSpec:
    return S.parse_spec(d, source=str(tmp_path / "spec.yaml") if tmp_path else "spec.yaml", base_dir=tmp_path or ".")


def write_spec(tmp_path: Path, d: dict) -> Path:
    p = tmp_path / "spec.yaml"
    p.write_text(yaml.safe_dump(d), encoding="utf-8")
    return p


# ----------------------------------------------------------------------------- spec and cases
@pytest.mark.parametrize("change, field", [
    ({"axes": {"params.nope": [1.0]}}, "axes.params.nope"),
    ({"axes": {"effects.stray_light.nope": [1.0]}}, "axes.effects.stray_light.nope"),
    ({"axes": {"effects.nope.weight": [1.0]}}, "axes.effects.nope.weight"),
    ({"axes": {"colour": [1]}}, "axes.colour"),
    ({"axes": {"seed": {"uniform": [0, 3]}}}, "axes.seed"),  # a distribution in a grid design
    ({"axes": {"seed": []}}, "axes.seed"),
    ({"design": {"type": "random"}}, "design.n"),
    ({"frames": 0}, "frames"),
    ({"compare": {"frames": "many"}}, "compare.frames"),
    ({"diagnose": {"candidates": ["nope"]}}, "diagnose.candidates[0]"),
    ({"bogus": 1}, "bogus"),
])
def test_bad_spec_names_file_and_field(tmp_path: Path, change: dict, field: str) -> None:
    d = json.loads(json.dumps(SPEC)) | change
    with pytest.raises(TofhilError) as err:
        S.load_spec(write_spec(tmp_path, d))
    assert err.value.field == field
    assert err.value.file == str(tmp_path / "spec.yaml")


def test_grid_and_random_designs() -> None:
    grid = S.expand_cases(spec_of(SPEC))
    assert len(grid) == 4
    assert {(c.params["params.card_reflectance"], c.params["seed"]) for c in grid} == {(0.4, 0), (0.4, 1), (0.8, 0),
                                                                                       (0.8, 1)}
    assert len({c.id for c in grid}) == 4
    rnd = dict(SPEC, design={"type": "random", "n": 50, "seed": 3},
               axes={"effects.stray_light.weight": {"uniform": [0.01, 0.05]},
                     "effects.stray_light.sigma_px": {"log_uniform": [2.0, 20.0]},
                     "seed": {"integers": [0, 4]}, "params.card_reflectance": [0.4, 0.8]})
    a, b = S.expand_cases(spec_of(rnd)), S.expand_cases(spec_of(rnd))
    assert [c.params for c in a] == [c.params for c in b]  # the design seed fixes the draws
    w = np.array([c.params["effects.stray_light.weight"] for c in a])
    s = np.array([c.params["effects.stray_light.sigma_px"] for c in a])
    seeds = {c.params["seed"] for c in a}
    assert w.min() >= 0.01 and w.max() <= 0.05 and s.min() >= 2.0 and s.max() <= 20.0
    assert seeds <= set(range(5)) and len(seeds) > 1
    assert {c.params["params.card_reflectance"] for c in a} == {0.4, 0.8}
    # the case's effects: the spec's block, overridden by the swept parameter
    eff = S.case_effects(spec_of(rnd), a[0].params)
    assert eff["stray_light"]["weight"] == a[0].params["effects.stray_light.weight"]


@pytest.mark.parametrize("path", sorted((Path(__file__).parents[2] / "configs" / "sweeps").glob("*.yaml")),
                         ids=lambda p: p.name)
def test_bundled_specs_validate(path: Path) -> None:
    spec = S.load_spec(path)
    assert S.expand_cases(spec)


def test_grid_forms_expand() -> None:
    d = dict(SPEC, axes={"params.card_reflectance": {"linspace": [0.2, 0.8, 4]}})
    vals = [c.params["params.card_reflectance"] for c in S.expand_cases(spec_of(d))]
    assert np.allclose(vals, [0.2, 0.4, 0.6, 0.8])


# ----------------------------------------------------------------------------- running
def _by_case(df: pd.DataFrame) -> dict[str, dict]:
    return {r["case"]: r for r in df.to_dict("records")}


def _missing(x) -> bool:
    return x is None or (isinstance(x, float) and math.isnan(x))


def _same(a, b) -> bool:
    """Equal values; a missing figure is None in a record and NaN in the table."""
    if _missing(a) or _missing(b):
        return _missing(a) and _missing(b)
    return a == b


def assert_table_matches_one_by_one(spec: S.SweepSpec, df: pd.DataFrame, tmp_path: Path,
                                    only: tuple[str, ...] | None = None) -> None:
    """Each case run alone, in this process, gives the very figures the table holds."""
    rows = _by_case(df)
    cases = [c for c in S.expand_cases(spec) if only is None or c.id in only]
    assert set(rows) == {c.id for c in cases}
    for case in cases:
        rec = S.run_case(spec, case, str(tmp_path / "alone"))
        assert rec["status"] == "ok", rec.get("error")
        for k, v in rec["metrics"].items():
            if k.endswith("seconds"):
                continue
            got = rows[case.id][k]
            assert _same(float(got) if isinstance(v, float) else got, v), (case.id, k, got, v)


def test_serial_sweep_table_report_and_shared_renders(tmp_path: Path) -> None:
    spec = spec_of(SPEC)
    before = sweep_run.RENDER_COUNT["renders"]
    sweep_run._TWINS.clear()
    res = S.run_sweep(spec, tmp_path / "out", workers=0)
    # 4 cases over 2 distinct scenes (the card's reflectance): 2 renders, the seeds, the
    # measurement with stray light and the twin reference share them
    assert sweep_run.RENDER_COUNT["renders"] - before == 2
    assert res.ran == 4 and res.failed == 0
    df = pd.read_parquet(tmp_path / "out" / "results.parquet")
    csv = pd.read_csv(tmp_path / "out" / "results.csv")
    assert list(df["case"]) == list(csv["case"]) and len(df) == 4
    assert {"params.card_reflectance", "seed", "camera.scale"} <= set(df.columns)
    rmse = [c for c in df.columns if c.startswith("compare.measured") and c.endswith("depth_rmse_m")]
    assert rmse, list(df.columns)
    # stray light pulls the measured depth away from the twin's: a non-zero error in every case
    assert (df[rmse[0]] > 0).all()
    assert len(list((tmp_path / "out" / "cases").glob("*.json"))) == 4
    page = (tmp_path / "out" / "report.html").read_text()
    assert "data:image/png;base64," in page and "params.card_reflectance" in page
    assert_table_matches_one_by_one(spec, df, tmp_path)


def test_no_effect_no_noise_equals_twin(tmp_path: Path) -> None:
    """Without noise and without any effect the measurement is the twin: zero depth error."""
    d = dict(SPEC, effects={}, noise=False, axes={"camera.scale": [0.25], "seed": [0, 5]})
    res = S.run_sweep(spec_of(d), tmp_path / "out", workers=0)
    col = [c for c in res.table.columns if c.startswith("compare.measured") and c.endswith("depth_rmse_m")][0]
    assert np.allclose(res.table[col].astype(float), 0.0, atol=1e-9)


def test_local_cluster_two_workers_and_failed_case(tmp_path: Path) -> None:
    """On a LocalCluster of 2 worker processes; a case that fails is recorded, the others run."""
    d = json.loads(json.dumps(SPEC))
    d["axes"]["camera.preset"] = ["holmlund_thesis", "no_such_preset"]
    d["axes"]["seed"] = [0]
    spec = spec_of(d)
    client = S.local_client(2)
    try:
        assert len(client.scheduler_info()["workers"]) == 2
        res = S.run_sweep(spec, tmp_path / "out", client=client)
    finally:
        cluster = client.cluster
        client.close()
        cluster.close()
    df = res.table
    assert len(df) == 4 and res.failed == 2
    bad = df[df["status"] == "error"]
    assert set(bad["camera.preset"]) == {"no_such_preset"}
    assert bad["error"].str.contains("no_such_preset").all()
    pids = {json.loads(p.read_text())["pid"] for p in (tmp_path / "out" / "cases").glob("*.json")}
    assert os.getpid() not in pids  # the cases ran in the workers
    ok_spec = spec_of(dict(d, axes={k: v for k, v in d["axes"].items() if k != "camera.preset"}))
    ok = df[df["status"] == "ok"].drop(columns=["camera.preset"])
    # the successful cases equal the same cases run alone (their ids differ: other axes)
    alone = S.run_sweep(ok_spec, tmp_path / "alone", workers=0).table
    cols = [c for c in ok.columns if c.startswith("compare.") and not c.endswith("seconds")]
    a = ok.sort_values("params.card_reflectance")[cols].reset_index(drop=True)
    b = alone.sort_values("params.card_reflectance")[cols].reset_index(drop=True)
    pd.testing.assert_frame_equal(a, b, check_dtype=False)


def test_diagnose_names_the_hidden_effect(tmp_path: Path) -> None:
    """A hidden range offset (a constant extra light path) is named by the diagnosis of each
    case; nothing hidden, nothing named."""
    d = {"scene": "wall_card", "frames": 4, "axes": {"camera.scale": [0.25], "effects": [
        {}, {"range_offset": {"path_m": 0.08}}]},
         "diagnose": {"max_effects": 1, "candidates": ["range_offset", "stray_light"]}}
    res = S.run_sweep(spec_of(d), tmp_path / "out", workers=0)
    df = res.table.set_index("effects")
    assert (res.table["status"] == "ok").all(), list(res.table["error"])
    assert df.loc["range_offset", "diagnose.causes"] == "range_offset"
    assert df.loc["none", "diagnose.causes"] == "none"
    assert df["diagnose.correct"].all()
    assert df.loc["range_offset", "diagnose.chi2_per_value.before"] > df.loc["range_offset",
                                                                           "diagnose.chi2_per_value.after_extended_scene"]


def test_refuses_to_overwrite_and_force(tmp_path: Path) -> None:
    spec = spec_of(dict(SPEC, axes={"camera.scale": [0.25], "seed": [0]}))
    S.run_sweep(spec, tmp_path / "out", workers=0)
    stamp = (tmp_path / "out" / "results.parquet").stat().st_mtime_ns
    with pytest.raises(TofhilError, match="--resume"):
        S.run_sweep(spec, tmp_path / "out", workers=0)
    assert (tmp_path / "out" / "results.parquet").stat().st_mtime_ns == stamp
    other = spec_of(dict(SPEC, axes={"camera.scale": [0.25], "seed": [1]}))
    with pytest.raises(TofhilError, match="another spec"):
        S.run_sweep(other, tmp_path / "out", workers=0, resume=True)
    res = S.run_sweep(other, tmp_path / "out", workers=0, force=True)
    assert list(res.table["seed"]) == [1] and len(list((tmp_path / "out" / "cases").glob("*.json"))) == 1


@pytest.mark.slow
def test_cli_default_engine_killed_and_resumed(tmp_path: Path, tofhil_cli) -> None:
    """The CLI on the default engine (a local cluster), killed mid-way with its workers, then
    resumed: finished cases are not redone and the table is that of the cases run alone."""
    d = json.loads(json.dumps(SPEC))
    d["axes"]["seed"] = [0, 1, 2]  # 6 cases
    spec_path = write_spec(tmp_path, d)
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "tofhil.cli", "sweep", str(spec_path), "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and len(list((out / "cases").glob("*.json"))) < 2 and proc.poll() is None:
            time.sleep(0.2)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the CLI and its worker processes
        proc.wait()
    done = {p.name: p.stat().st_mtime_ns for p in (out / "cases").glob("*.json")}
    assert 2 <= len(done) < 6, f"{len(done)} cases finished before the kill"
    r = tofhil_cli("sweep", spec_path, "--out", out)
    assert r.returncode == 2 and "--resume" in r.stderr
    r = tofhil_cli("sweep", spec_path, "--out", out, "--resume", "--workers", "2")
    assert r.returncode == 0, r.stderr
    assert f"{6 - len(done)} case(s) run, {len(done)} already done" in r.stdout
    for name, stamp in done.items():
        assert (out / "cases" / name).stat().st_mtime_ns == stamp  # not redone
    df = pd.read_parquet(out / "results.parquet")
    assert len(df) == 6 and (df["status"] == "ok").all()
    # one case finished before the kill and one after the resume, each run alone here
    spec = S.load_spec(spec_path)
    first, last = sorted(done)[0][:-5], sorted(set(df["case"]) - {n[:-5] for n in done})[0]
    assert_table_matches_one_by_one(spec, df[df["case"].isin([first, last])], tmp_path, only=(first, last))


def test_cli_bad_spec_one_line(tmp_path: Path, tofhil_cli) -> None:
    p = write_spec(tmp_path, dict(SPEC, axes={"params.nope": [1]}))
    r = tofhil_cli("sweep", p, "--out", tmp_path / "out")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "axes.params.nope" in r.stderr and str(p) in r.stderr
    assert not (tmp_path / "out").exists()


def test_batch_compare_over_sessions(tmp_path: Path, tofhil_cli) -> None:
    """``tofhil batch compare`` over a glob of sessions against one reference: one table."""
    from tofhil.sim.pipeline import simulate_session
    from tofhil.sim.scene import load_scene

    import dataclasses

    scene = load_scene("wall_card")
    scene = dataclasses.replace(scene, camera=scene.camera.scaled(0.25))
    for i in range(2):
        simulate_session(scene, tmp_path / f"s{i}.h5", frames=2, seed=i)
    simulate_session(scene, tmp_path / "ref.h5", frames=1, noise=False)
    r = tofhil_cli("batch", "compare", str(tmp_path / "s*.h5"), "--reference", tmp_path / "ref.h5",
                   "--out", tmp_path / "out", "--workers", "0")
    assert r.returncode == 0, r.stderr
    df = pd.read_csv(tmp_path / "out" / "results.csv")
    assert [Path(p).name for p in df["session"]] == ["s0.h5", "s1.h5"]
    assert (df["status"] == "ok").all()
    col = [c for c in df.columns if c.endswith("depth_rmse_m") and c.startswith("compare.measured")][0]
    assert (df[col] > 0).all()  # shot and read noise against a noise-free reference


# ----------------------------------------------------------------------------- capture cases
CAPTURE_SPEC = {
    "name": "capture",
    "scene": "wall_card",
    "capture": {"device": "emulator", "frames": 2},
    "effects": {"range_offset": {"path_m": 0.1}},  # what the emulated bench has and the twin lacks
    "axes": {"capture.integration_time_us": [100.0, 400.0]},
    "compare": {"reference": "twin", "frames": 2},
}


@pytest.mark.parametrize("change, field", [
    ({"capture": {"device": "usb"}, "axes": {"params.card_reflectance": [0.4]}}, "axes.params.card_reflectance"),
    ({"capture": {"device": "emulator"}, "axes": {"camera.scale": [0.5]}}, "axes.camera.scale"),
    ({"capture": {"device": "emulator", "roi": [4, 4, 2, 12]}}, "capture.roi"),
    ({"capture": {"device": "emulator", "mode": "grayscale"}}, "capture.mode"),
    ({"capture": {"frames": 2}}, "capture.device"),
    ({"capture": {"device": "emulator"}, "simulate": True}, "simulate"),
    ({"capture": None, "axes": {"capture.channel": [1]}}, "capture"),
    ({"axes": {"capture.channel": [99]}}, "axes.capture.channel[0]"),
])
def test_bad_capture_spec_names_the_field(change: dict, field: str) -> None:
    d = {k: v for k, v in (json.loads(json.dumps(CAPTURE_SPEC)) | change).items() if v is not None}
    with pytest.raises(TofhilError) as e:
        spec_of(d)
    assert f"field '{field}'" in str(e.value) or f"{field}:" in str(e.value), str(e.value)


def test_capture_cases_from_the_emulated_bench(tmp_path: Path) -> None:
    """Each case captures from the emulated TOFcam635 looking at the scene with the case's
    integration time; the twin re-renders with the capture's settings. Physics: the collected
    modulation grows linearly with the exposure (4x the time, 4x the tap amplitude), and the
    bench's hidden 0.1 m extra light path reads 0.05 m farther than the twin in both cases."""
    from tofhil.demod import phasor
    from tofhil.session import open_session

    res = S.run_sweep(spec_of(CAPTURE_SPEC), tmp_path / "out", workers=0)
    df = res.table.set_index("capture.integration_time_us")
    assert (res.table["status"] == "ok").all(), list(res.table["error"])
    amp = {}
    for case in S.expand_cases(spec_of(CAPTURE_SPEC)):
        cdir = tmp_path / "out" / "cases" / case.id
        with open_session(cdir / "measured.h5") as s, open_session(cdir / "twin.h5") as t:
            assert s.device["model"] != "tofhil-sim" and s.device["settings"]["integration_time_s"] == pytest.approx(
                case.params["capture.integration_time_us"] * 1e-6)
            frame = s.raw_frame(0)
            assert t.camera.shape == s.camera.shape and np.allclose(t.freq_hz, s.freq_hz)
            amp[case.params["capture.integration_time_us"]] = np.median(np.abs(phasor(frame.taps.astype(float),
                                                                                      frame.theta_rad)))
    assert amp[400.0] / amp[100.0] == pytest.approx(4.0, rel=0.03)
    col = "compare.measured.regions.all.depth_residual_m.median"
    assert col in df.columns, [c for c in df.columns if c.startswith("compare.measured.regions.all")]
    assert np.allclose(df[col].astype(float), 0.05, atol=0.005)


def test_retry_failed_reruns_only_the_failed(tmp_path: Path) -> None:
    d = dict(SPEC, axes={"camera.scale": [0.25], "seed": [0], "camera.preset": ["holmlund_thesis", "no_such_preset"]})
    spec = spec_of(d)
    out = tmp_path / "out"
    assert S.run_sweep(spec, out, workers=0).failed == 1
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "cases").glob("*.json")}
    assert S.run_sweep(spec, out, workers=0, resume=True).ran == 0
    with pytest.raises(TofhilError, match="--resume"):
        S.run_sweep(spec, out, workers=0, retry_failed=True)
    res = S.run_sweep(spec, out, workers=0, resume=True, retry_failed=True)
    assert res.ran == 1 and res.failed == 1
    bad = res.table.loc[res.table["status"] != "ok", "case"].item()
    for name, stamp in stamps.items():
        assert ((out / "cases" / name).stat().st_mtime_ns == stamp) == (name != f"{bad}.json")


def test_cli_against_a_running_scheduler_and_device_lock(tmp_path: Path, tofhil_cli) -> None:
    """``--scheduler ADDRESS``: the CLI connects to a cluster it did not start (here one on
    the loopback); the cases run in that cluster's worker. Captures from one device hold a
    cluster-wide lock: two tasks never hold it at once."""
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                           host="127.0.0.1", scheduler_port=0)
    try:
        with Client(cluster) as client:
            def hold(i: int) -> tuple[float, float]:
                with S.device_lock("usb:1:2"):
                    t0 = time.time()
                    time.sleep(0.3)
                    return t0, time.time()

            spans = sorted(client.gather(client.map(hold, range(4), pure=False)))
            assert all(a[1] <= b[0] for a, b in zip(spans, spans[1:])), spans
            worker_pids = set(client.run(os.getpid).values())
        d = dict(SPEC, axes={"camera.scale": [0.25], "seed": [0]})
        r = tofhil_cli("sweep", write_spec(tmp_path, d), "--out", tmp_path / "out", "--scheduler",
                       cluster.scheduler_address)
        assert r.returncode == 0, r.stderr
        assert f"connecting to the Dask scheduler at {cluster.scheduler_address}" in r.stderr
        pids = {json.loads(p.read_text())["pid"] for p in (tmp_path / "out" / "cases").glob("*.json")}
        assert pids and pids <= worker_pids, (pids, worker_pids)
    finally:
        cluster.close()


# ----------------------------------------------------------------------------- the PSF calibration
def test_calibrated_psf_sweep_removes_the_dark_square_error(tmp_path: Path) -> None:
    """The stray-light study's calibrated-PSF method as a spec: ONE calibration on another
    scene (wall and card against its stray-light-free twin), then every case corrected with
    it. The stray light is two of the study's lobes and its veil; the correction removes most
    of the square's error at 50 % and 10 % reflectivity (lower reflectivities clip at the
    scene sensor's zero black level: benchmarks/straylight_study.py raises it)."""
    lens = {"gaussians": [[0.02, 3.0, 3.0], [0.03, 15.0, 12.0]], "veil": 0.01}
    d = {"name": "sl", "scene": "dark_square_card", "frames": 1, "noise": False,
         "effects": {"stray_light": lens},
         "axes": {"camera.scale": [0.5], "params.square_reflectance": [0.5, 0.1]},
         "calibrate": {"scene": "wall_card", "reference": "twin", "form": "gaussian"},
         "compare": {"reference": "twin", "frames": 1, "corrections": ["psf:psf=@calibration"]}}
    logs: list[str] = []
    res = S.run_sweep(spec_of(d), tmp_path / "out", workers=0, log=logs.append)
    assert (res.table["status"] == "ok").all(), list(res.table["error"])
    assert (tmp_path / "out" / "calibration" / "psf.json").is_file()
    assert any(m.startswith("PSF calibrated") for m in logs)
    before = res.table["compare.measured.regions.square.depth_rmse_m"].astype(float)
    after = res.table["compare.psf:psf=@calibration.regions.square.depth_rmse_m"].astype(float)
    assert (before > 1e-2).all() and (after < 0.1 * before).all(), (list(before), list(after))
    with pytest.raises(TofhilError, match="compare.corrections"):
        spec_of({k: v for k, v in d.items() if k != "calibrate"})
    with pytest.raises(TofhilError, match="axes.camera.scale"):
        spec_of(dict(d, axes={"camera.scale": [0.5, 0.25]}))
