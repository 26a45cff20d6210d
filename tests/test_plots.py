"""The figures: every one rendered from a short run through the real CLI, and checked to be
a valid image with content; the report page embeds them; the files they read round-trip."""

import base64
import re

import matplotlib.image as mpimg
import numpy as np
import pytest

from filters.output import (
    nis_path,
    read_estimates_csv,
    read_nis_csv,
    write_estimates_csv,
    write_nis_csv,
)
from filters.pipeline import run_filter
from ngnav.plots import RUN_PLOT_FILES, outage_spans
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight
from tests.helpers import run_cli

SHORT = "run.rate_hz=200"
RUN_FIGURES = ("trajectory", "position", "velocity", "attitude", "rate", "errors", "nis")


def _assert_image_with_content(path):
    """A PNG that decodes, of a sensible size, with drawing on it (not one flat colour)."""
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", path
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] >= 300 and img.shape[1] >= 500, (path, img.shape)
    rgb = img[..., :3].reshape(-1, 3)
    colours = np.unique(np.round(rgb * 255).astype(np.uint8), axis=0)
    assert colours.shape[0] > 20, (path, colours.shape)  # lines, text, bands
    assert np.mean(np.all(rgb > 0.98, axis=1)) < 0.97, path  # not a blank canvas


@pytest.fixture(scope="module")
def plotted(tmp_path_factory):
    run = tmp_path_factory.mktemp("plots") / "run"
    sets = ["--set", SHORT, "--set", "gps.outage_start_s=20", "--set", "gps.outage_s=5"]
    run_cli("simulate", "--scenario", "tactical", *sets, "--out", str(run))
    run_cli("run", str(run))
    proc = run_cli("plot", str(run))
    return run, proc


def test_every_run_figure_is_an_image_with_content(plotted):
    run, proc = plotted
    for name in RUN_FIGURES:
        _assert_image_with_content(run / "plots" / f"{name}.png")
    # what a new flight into the same folder removes (ngnav.plots.RUN_PLOT_FILES) is all it wrote
    assert {p.name for p in (run / "plots").iterdir()} <= set(RUN_PLOT_FILES)
    assert "7 figures" in proc.stdout
    assert "GPS outages (shaded): 19.9-25.0 s" in proc.stdout  # last fix to next fix


def test_the_report_embeds_every_figure_and_the_summary(plotted):
    run, _ = plotted
    page = (run / "plots" / "report.html").read_text()
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(images) == len(RUN_FIGURES)
    for blob in images:
        assert base64.b64decode(blob)[:8] == b"\x89PNG\r\n\x1a\n"
    assert "against truth.csv: horizontal RMS" in page
    assert "GPS positions rejected by the gate" in page


def test_plot_without_estimates_says_what_to_run(tmp_path):
    (tmp_path / "config.toml").write_text("")
    proc = run_cli("plot", str(tmp_path), check=False)
    assert proc.returncode == 2
    err = proc.stderr.strip()
    assert "\n" not in err and "no such file; run `ngnav run" in err
    proc = run_cli("plot", str(tmp_path / "nowhere"), check=False)
    assert proc.returncode == 2 and "not a run directory" in proc.stderr


def test_consistency_and_paper_figures(tmp_path):
    run_cli("consistency", "--scenario", "tactical", "--set", SHORT, "--runs", "2",
            "--workers", "1", "--plot", str(tmp_path / "mc"))  # fmt: skip
    _assert_image_with_content(tmp_path / "mc" / "nees.png")
    run_cli("paper", "--plot", str(tmp_path / "paper"))
    _assert_image_with_content(tmp_path / "paper" / "table1.png")


def test_estimates_and_nis_files_read_back(tmp_path):
    sim = simulate_flight(load_flight("tactical", [SHORT]), 0)
    res = run_filter(sim.samples, sim.fixes, sim.config)
    path = tmp_path / "estimates.csv"
    write_estimates_csv(path, res.estimates, sim.config)
    write_nis_csv(nis_path(path), res.innovations)
    est, back = res.estimates, read_estimates_csv(path)
    np.testing.assert_allclose(back.t_s, est.t_s, atol=1e-6)
    np.testing.assert_allclose(back.pos_ned_m, est.pos_ned_m, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(back.q_nb, est.q_nb, rtol=1e-5, atol=1e-6)
    sig = np.sqrt(np.einsum("eii->ei", est.cov_nav))
    np.testing.assert_allclose(np.sqrt(np.einsum("eii->ei", back.cov_nav)), sig, rtol=1e-5)
    assert np.count_nonzero(back.cov_nav[0] - np.diag(np.diag(back.cov_nav[0]))) == 0
    nis = read_nis_csv(nis_path(path))
    assert nis_path(path).name == "estimates.nis.csv"
    np.testing.assert_array_equal(nis.pos_accepted, res.innovations.pos_accepted)
    np.testing.assert_allclose(nis.nis_pos, res.innovations.nis_pos, rtol=1e-5)


def test_outage_spans():
    t = np.array([0.0, 0.2, 0.4, 3.4, 3.6, 3.8, 10.0])
    assert outage_spans(t, 1.0) == [(0.4, 3.4), (3.8, 10.0)]
    assert outage_spans(t, 5.0) == [(3.8, 10.0)]
    assert outage_spans(t[:1], 1.0) == []


def test_demo_shows_the_whole_chain(tmp_path):
    """``make run``'s command: Table 1, a flight beside its bound, the report it wrote."""
    proc = run_cli("demo", "--out", str(tmp_path / "demo"))
    out = proc.stdout
    assert "GM(1,1) compensation changes the mean absolute error" in out
    rows = dict(
        (line[:19].strip(), [float(v) for v in line[19:].split()])
        for line in out.splitlines()
        if line.startswith("   ") and line[19:].replace(".", "").replace(" ", "").isdigit()
    )
    assert set(rows) >= {"horizontal, m", "tilt, deg", "heading, deg", "rate, deg/s"}
    for name, (got, bound) in rows.items():
        # a working filter lands near its bound; a broken one is many times off
        assert 0.3 * bound < got < 3.0 * bound, (name, got, bound)
    report = tmp_path / "demo" / "run" / "plots" / "report.html"
    assert f"Open {report} in a browser." in out
    _assert_image_with_content(tmp_path / "demo" / "paper" / "table1.png")


def test_the_binary_estimates_keep_the_full_covariance(tmp_path):
    from filters.output import npz_path, write_estimates_npz
    from ngnav import api

    sim = simulate_flight(load_flight("tactical", [SHORT]), 0)
    res = run_filter(sim.samples, sim.fixes, sim.config)
    path = npz_path(tmp_path / "estimates.csv")
    assert path.name == "estimates.npz"
    write_estimates_npz(path, res)
    est, fin = api.read_estimates(path)
    np.testing.assert_array_equal(est.cov_nav, res.estimates.cov_nav)  # bit for bit
    np.testing.assert_array_equal(est.q_nb, res.estimates.q_nb)
    np.testing.assert_array_equal(est.aoa_sigma_rad, res.estimates.aoa_sigma_rad)
    assert np.count_nonzero(est.cov_nav[-1][0:3, 3:6])  # correlations, not only sigmas
    np.testing.assert_array_equal(fin.cov, res.final.cov)
    assert fin.state_blocks == res.final.state_blocks
    np.testing.assert_array_equal(fin.block_cov("dr"), res.final.block_cov("dr"))
    np.testing.assert_array_equal(fin.dr_m, res.final.dr_m)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"bad\.npz: not an estimates file"):
        api.read_estimates(tmp_path / "bad.npz")


def test_ngnav_run_writes_the_binary_estimates(plotted):
    from ngnav import api

    run, _ = plotted
    est, fin = api.read_estimates(run / "estimates.npz")
    csv_est, _ = api.read_estimates(run / "estimates.csv")
    np.testing.assert_allclose(est.pos_ned_m, csv_est.pos_ned_m, rtol=1e-5, atol=1e-5)
    assert fin.cov.shape[0] == sum(d for _, d in fin.state_blocks) > 12


def test_the_python_api_draws_the_same_report(plotted, tmp_path):
    from ngnav import api

    run, _ = plotted
    got = api.plot(run, out=tmp_path / "figures")
    assert sorted(p.stem for p in got.figures) == sorted(RUN_FIGURES)
    assert got.report == tmp_path / "figures" / "report.html" and got.report.is_file()
    assert any(line.startswith("against truth.csv") for line in got.summary)
