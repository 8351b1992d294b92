"""The comparison report of a batch identification (one self-contained HTML file), on rows
made by hand: seed 004 Table 3 (actuators 2 and 4, cvs), seed 002 cylinder A (nominal) and
a failed row. No model runs: fast."""
import base64
import html
import math
import re

import numpy as np
import pytest

from combined_reality.batch.report import efficiency, friction_curve, render_batch_report, write_batch_report
from sim.friction_models import FRICTION_MODELS

PA, PS = 1.013e5, 7.013e5  # atmosphere, supply (6 bar gauge, seed 004 section 3)
CYL = dict(status="ok", supply_pressure=PS, atmosphere=PA, source="recorded", n_runs=3, mean_dp=1.2e5,
           mean_pc=1.5e5, rmse_x=31e-6, r2_x=0.99998, rmse_p1=2900.0, rmse_p2=3100.0, solver_status="converged",
           iterations=12, wall_s=6.6)


def _cvs(name, bore, fs, fc, b, vs, max_speed, **extra):
    """A cvs row from seed 004 Table 3 (magnitudes; vs in mm/s as printed)."""
    r = dict(CYL, name=name, model="cvs", bore=bore, rod=0.4 * bore, stroke=0.1, max_speed=max_speed,
             Fs_pos=fs[0], Fs_neg=fs[1], Fc_pos=fc[0], Fc_neg=fc[1], B_pos=b[0], B_neg=b[1],
             vs_pos=vs[0] / 1e3, vs_neg=vs[1] / 1e3)
    r.update(extra)
    return r


ACT2 = _cvs("actuator 2 (Norgren 32 x 100)", 0.032, (22, 20), (16.87, 13.47), (178.85, 165.59), (3.42, 6.16), 0.35,
            Fc_pos_std=0.21, Fc_neg_std=0.18, B_pos_std=2.7)
ACT4 = _cvs("actuator 4 (Norgren 50 x 400)", 0.05, (6, 11), (1.59, 6.10), (203.71, 259.13), (8.5, 8.9), 0.15)
NOMINAL = dict(CYL, name="seed 002 cylinder A", model="nominal", source="simulated", bore=0.032, rod=0.012,
               stroke=0.1, max_speed=0.25, mean_dp=1.6e5, Fc=24.8, Fv=13.45, kp=2.89e-5, Fc_std=0.12,
               truth_Fc=24.0, truth_Fv=13.40, truth_kp=2.89e-5,  # Fc 3.3 % off the truth: within 5 %
               cylinder="seed 002 cylinder A (32 x 100)", config="configs/cyl_a_32x100.toml", duration_s=20.0)
FAILED = dict(name="a<b&c", status="failed", model="cvs", config="configs/x&y.toml",
              error="simulation diverged: p1 < 0 & x > stroke")
ROWS = [ACT2, ACT4, NOMINAL, FAILED]


def _eq3(v, fs, fc, b, vs, delta=2.0):
    """seed 004 Eq. 3 per direction, retraction negative: F = Fc + B v + (Fs - Fc) exp(-(v / vs)^delta)."""
    v = np.asarray(v, float)
    a = np.abs(v)
    pos = fc[0] + b[0] * a + (fs[0] - fc[0]) * np.exp(-(a / vs[0]) ** delta)
    neg = fc[1] + b[1] * a + (fs[1] - fc[1]) * np.exp(-(a / vs[1]) ** delta)
    return np.where(v > 0, pos, -neg)


def _section(text: str, heading: str) -> str:
    start = text.index(heading)
    end = text.find("<h2>", start + 1)
    return text[start:end if end > 0 else len(text)]


def _cells(section: str, name: str) -> list[str]:
    """The text of the cells of the table row that starts with `name` (escaped as in HTML)."""
    row = re.search(r'<tr><td class="name">' + re.escape(html.escape(name)) + r"(.*?)</tr>", section, re.S)
    assert row, name
    cells = re.findall(r"<td[^>]*>(.*?)</td>", '<td class="name">' + row.group(0)[len('<tr><td class="name">'):], re.S)
    return [html.unescape(re.sub(r"<[^>]+>", " ", c)).strip() for c in cells]


def _images(text: str) -> list[bytes]:
    return [base64.b64decode(m) for m in re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    d = tmp_path_factory.mktemp("batch")
    path, png = d / "out" / "report.html", d / "png"
    path.parent.mkdir()  # writers create no folders (the command line checks them first)
    write_batch_report(ROWS, path, png_dir=png, title="Batch <test>")
    return path.read_text(encoding="utf-8"), png


# ------------------------------------------------------------------ the curves

def test_cvs_curve_is_seed_004_eq_3():
    v = np.array([1e-4, 0.002, 0.00342, 0.01, 0.2, -0.001, -0.00616, -0.03, -0.3])
    want = _eq3(v, (22, 20), (16.87, 13.47), (178.85, 165.59), (0.00342, 0.00616))
    np.testing.assert_allclose(friction_curve(ACT2, v), want, rtol=1e-12, atol=1e-9)
    # by hand at the Stribeck velocity of extension: Fc + B vs + (Fs - Fc) / e
    assert friction_curve(ACT2, [0.00342])[0] == pytest.approx(16.87 + 178.85 * 0.00342 + 5.13 / math.e)


def test_nominal_curve_opposes_motion_with_the_pressure_term_at_the_mean_dp():
    v = np.array([0.05, -0.1])
    F = friction_curve(NOMINAL, v)
    np.testing.assert_allclose(F, [24.8 + 13.45 * 0.05 + 2.89e-5 * 1.6e5, -(24.8 + 13.45 * 0.1 + 2.89e-5 * 1.6e5)])


def test_a_curve_from_csv_text_fills_missing_parameters_with_the_model_defaults():
    row = {k: str(v) for k, v in ACT2.items()}  # as read from results.csv
    np.testing.assert_allclose(friction_curve(row, [0.01]), friction_curve(ACT2, [0.01]))
    # B_neg missing: the cvs model's default, the other parameters the row's
    b_neg = FRICTION_MODELS["cvs"].defaults()["B_neg"]
    assert b_neg != ACT2["B_neg"]
    v = np.array([0.01, -0.01, -0.2])
    no_b = {k: x for k, x in row.items() if k != "B_neg"}
    want = _eq3(v, (22, 20), (16.87, 13.47), (178.85, b_neg), (0.00342, 0.00616))
    np.testing.assert_allclose(friction_curve(no_b, v), want, rtol=1e-12)
    with pytest.raises(ValueError, match="unknown friction model"):
        friction_curve(dict(ACT2, model="magic"), [0.01])
    with pytest.raises(ValueError, match="none of the parameters"):
        friction_curve({"name": "x", "model": "cvs"}, [0.01])


# ------------------------------------------------------------------ the report

def test_headline_counts_and_the_failed_row_escaped(report):
    text, _ = report
    head = re.search(r'<div class="headline[^"]*">(.*?)</div>', text, re.S).group(1)
    assert "4 cylinders in the batch: 3 identified, 1 failed." in head
    assert "<title>Batch &lt;test&gt;</title>" in text
    fail = _section(text, "<h2>Not identified</h2>")
    assert "a&lt;b&amp;c" in fail and "simulation diverged: p1 &lt; 0 &amp; x &gt; stroke" in fail
    assert "configs/x&amp;y.toml" in fail
    assert "a<b&c" not in text and "p1 < 0" not in text


def _table3_cells(t3: str, name: str) -> list[str]:
    """cylinder, model, Fs ext/retr, Fc ext/retr, B ext/retr, vs ext/retr (mm/s), other parameters: from the
    extension and retraction tables and the table of other parameters (as one row of seed 004's Table 3)."""
    ext = _cells(t3[t3.index("<h3>extension"):t3.index("<h3>retraction")], name)
    ret = _cells(t3[t3.index("<h3>retraction"):], name)
    others = t3[t3.index("<h3>other parameters"):] if "<h3>other parameters" in t3 else ""
    other = _cells(others, name)[1] if html.escape(name) in others else "—"
    return ext[:2] + [c for pair in zip(ext[2:6], ret[2:6]) for c in pair] + [other]


def test_table_3_is_split_per_direction_so_that_it_fits_the_page(report):
    text, _ = report
    t3 = _section(text, "<h2>Friction parameters")
    assert t3.split("<h3>Against")[0].count("<table>") == 3 and "<h3>extension</h3>" in t3 and "<h3>retraction</h3>" in t3
    # every table that is not inside another scrolls sideways instead of running off the page
    assert text.count('<div class="scroll"><table') == text.count("<table") - text.count('<table style="margin:0">')
    header = re.search(r"<h3>extension</h3>\s*<div class=\"scroll\"><table><tr>(.*?)</tr>", t3, re.S).group(1)
    assert header.count("<th>") == 6  # cylinder, model and four quantities: half the columns of one table


def test_table_3_shows_the_values_per_direction(report):
    text, _ = report
    t3 = _section(text, "<h2>Friction parameters")
    # cylinder, model, Fs ext/retr, Fc ext/retr, B ext/retr, vs ext/retr (mm/s), other
    c2 = _table3_cells(t3, ACT2["name"])
    assert c2[1] == "cvs"
    assert c2[2:4] == ["22.00", "20.00"]
    assert c2[4] == "16.87 ± 0.21" and c2[5] == "13.47 ± 0.18"
    assert c2[6].startswith("178.8") and "± 2.7" in c2[6] and c2[7].startswith("165.6")
    assert c2[8].startswith("3.42") and c2[9].startswith("6.16")  # mm/s
    assert "delta = 2" in c2[10] and "fixed" in c2[10]
    c4 = _table3_cells(t3, ACT4["name"])
    assert c4[4].startswith("1.59") and c4[5].startswith("6.10") and c4[8].startswith("8.50")
    assert "±" not in "".join(c4[2:10])  # no std given
    cn = _table3_cells(t3, NOMINAL["name"])
    assert cn[1] == "nominal"
    assert cn[2] == cn[3] == cn[8] == cn[9] == "—"  # the nominal model has no Fs, no Stribeck velocity
    assert cn[4] == cn[5] == "24.80 ± 0.12" and cn[6] == cn[7] == "13.45"
    assert "kp = 2.89" in cn[10] and "N/bar" in cn[10]
    assert "a&lt;b&amp;c" not in t3  # failed rows are not in the comparison


def test_truth_table_marks_errors_beyond_5_percent():
    off = dict(NOMINAL, name="off", Fv=15.0)  # Fv 11.9 % above its truth
    text = render_batch_report([NOMINAL, off], plots={})
    truth = _section(text, "<h3>Against the truth")
    good = truth[truth.index(html.escape(NOMINAL["name"])):truth.index('"name">off')]
    assert re.search(r'<td class="num" title="[^"]*">\+3\.3 %</td>', good)  # Fc: (24.8 - 24) / 24
    assert "bad" not in good
    bad = truth[truth.index('"name">off'):]
    assert re.search(r'<td class="num bad" title="identified 15\.00, truth 13\.40[^"]*">\+11\.9 %</td>', bad)
    assert "1 of 6 parameters is off by more than 5 %: off: Fv" in text


def test_efficiency_factor_is_seed_004_eq_1(report):
    text, _ = report
    pA2 = (PS - PA) * math.pi * 0.032 ** 2 / 4  # 6 bar gauge on the 32 mm bore: 482.5 N
    at_ref = 16.87 + 178.85 * 0.2 + (22 - 16.87) * math.exp(-(0.2 / 0.00342) ** 2)
    m = efficiency(ACT2)
    assert m["breakaway_extension"] == pytest.approx(22 / pA2)  # Fs
    assert m["breakaway_retraction"] == pytest.approx(20 / pA2)
    assert m["extension"] == pytest.approx(at_ref / pA2)
    assert m["retraction"] == pytest.approx((13.47 + 165.59 * 0.2) / pA2)
    mn = efficiency(NOMINAL)  # no Fs: Fc, with the pressure term at the mean |p1 - p2|
    assert mn["breakaway_extension"] == pytest.approx((24.8 + 2.89e-5 * 1.6e5) / pA2)
    # Threlfall's curve rises from 0 at rest: its breakaway is the plateau Fc of each direction
    mt = efficiency(dict(CYL, model="threlfall", bore=0.032, Fc_pos=10.0, Fc_neg=9.0))
    assert (mt["breakaway_extension"], mt["breakaway_retraction"]) == pytest.approx((10.0 / pA2, 9.0 / pA2))
    sec = _section(text, "<h2>Efficiency factor")
    c2 = _cells(sec, ACT2["name"])
    assert c2[2:5] == ["6.00", "8.04", "483"]  # bar gauge, cm², N
    assert c2[5:9] == [f"{22 / pA2:.3f}", f"{20 / pA2:.3f}", f"{at_ref / pA2:.3f}",
                       f"{(13.47 + 165.59 * 0.2) / pA2:.3f}"]
    # actuator 4 never ran at 0.2 m/s (max 0.15 m/s): extrapolated, and marked so
    c4 = _cells(sec, ACT4["name"])
    assert c4[7].endswith("*") and "extrapolated" in sec
    assert "0.05–0.20" in sec and "Festo (1996) 0.10" in sec and "Pinches and Callear (1997) 0.02–0.06" in sec


def test_cylinder_data_in_the_users_units(report):
    text, _ = report
    c = _cells(_section(text, "<h2>The cylinders"), NOMINAL["name"])
    assert "seed 002 cylinder A (32 x 100)" in c[0] and "configs/cyl_a_32x100.toml" in c[0]
    # source, runs, duration (s), bore, rod, stroke (mm), supply (bar gauge), |p1 - p2|, pc (bar), fastest (mm/s)
    assert c[1:] == ["simulated", "3", "20.0", "32.0", "12.0", "100", "6.00", "1.60", "1.50", "250"]


def test_fit_quality_in_the_users_units(report):
    text, _ = report
    c2 = _cells(_section(text, "<h2>Fit quality"), ACT2["name"])
    assert c2[2] == "31.0" and c2[3] == "0.999980" and c2[4] == "2.90" and c2[5] == "3.10"  # um, R², kPa
    assert c2[6] == "converged" and c2[7] == "12"


def test_plots_are_embedded_pngs_and_written_to_the_folder(report):
    text, png = report
    imgs = _images(text)
    assert len(imgs) == 2
    assert all(i.startswith(b"\x89PNG\r\n\x1a\n") and len(i) > 10_000 for i in imgs)
    files = sorted(png.iterdir())
    assert [p.name for p in files] == ["a_friction_maps.png", "b_efficiency.png"]
    assert [p.read_bytes() for p in files] == imgs


# ------------------------------------------------------------------ odd batches

def test_no_identified_cylinder_says_so():
    text = render_batch_report([FAILED, dict(name="s", status="skipped", error="no runs")])
    assert "2 cylinders in the batch: 0 identified, 1 failed, 1 skipped." in text
    assert "No cylinder was identified" in text and "no runs" in text
    assert "<img" not in text and "Table 3" not in text
    assert "holds no cylinders" in render_batch_report([])


def test_odd_rows_render(tmp_path):
    nan = float("nan")
    odd = [
        {k: str(v) for k, v in ACT4.items()},  # every value as text, as from the CSV
        dict(ACT2, name="$x$ _lead", Fs_pos=nan, Fc_pos_std=nan, max_speed=None, rmse_x="", r2_x=None,
             bore=None),  # NaN, missing std, no bore (no efficiency), a name matplotlib would misread
        dict(name="mystery", status="ok", model="magic", Fc=3.0),  # unknown model
        dict(CYL, name="bel", model="belforte", bore=0.04, FA_pos=8.0, FA_neg=6.0, K2_pos=2e-5, K2_neg=2e-5,
             mean_pc=None),  # pressure model without counter pressure
    ]
    write_batch_report(odd, tmp_path / "odd.html", tmp_path / "png")
    text = (tmp_path / "odd.html").read_text(encoding="utf-8")
    assert "4 cylinders in the batch: 4 identified, 0 failed." in text
    t3 = _section(text, "<h2>Friction parameters")
    c = _table3_cells(t3, "$x$ _lead")
    assert c[2] == "n/a" and c[4] == "16.87"  # Fs_pos NaN: not available; Fc_pos without its NaN std
    assert "magic" in t3 and "unknown" in t3
    maps = _section(text, "<h2>Friction against velocity")
    assert "Not drawn: mystery (unknown model &#x27;magic&#x27;)" in maps
    assert "mean_pc not in the results: taken as 0" in maps
    assert "model&#x27;s defaults: $x$ _lead: Fs_pos; bel: K1_pos, K1_neg, alpha_pos" in maps
    assert "curve drawn up to 500 mm/s: $x$ _lead" in maps
    eff = _cells(_section(text, "<h2>Efficiency factor"), "$x$ _lead")
    assert eff[5:9] == ["n/a"] * 4
    assert len(_images(text)) == 2


def test_a_single_cylinder():
    text = render_batch_report([ACT2])
    assert "1 cylinder in the batch: 1 identified, 0 failed." in text
    assert "Not identified" not in text
    assert len(_images(text)) == 2
