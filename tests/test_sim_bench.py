"""`haactl bench sim` pieces on tiny workloads (a smoke run: they measure, and report what they measured)."""

from __future__ import annotations

from haa.lab.experiments import sim as simbench
from haactl import benchtables


def test_bench_sim_pieces_run_and_report() -> None:
    step = simbench.bench_stepping(2.0, sensors=True)
    assert step["avatars"] == 10 and step["sim_seconds"] == 2.0 and step["x_realtime_cpu"] > 0
    cam = simbench.bench_camera("small", "seeker", 4)
    assert cam["size"] == "320x240" and cam["render_cpu"]["n"] == 4 and cam["markers_expected"] >= cam["markers_found"]
    sens = simbench.bench_sensors(20)
    assert sens["sonar_scan_cpu"]["n"] == 20 and sens["avatars_in_world"] == 10
    r = {"stepping": [step, step], "camera": [cam], "sensors": sens}
    r["camera"][0]["recall"] = r["camera"][0]["recall"] or 0.0
    text = benchtables.sim(r)
    assert "| physics + odometry + sonar 1 Hz + detections 1 Hz | 2 s |" in text
    assert "| small | basic | 320x240 |" in text and "| sonar scan (5 sonars x 9 rays) |" in text
