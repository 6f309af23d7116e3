"""The mpg-render command line: outputs, overrides, errors, interruption."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np

import mpg

CLI = [sys.executable, "-m", "mpg.cli"]
SMALL = ["-D", "res_x=32", "-D", "res_y=24"]


def run(args, **kw):
    return subprocess.run(CLI + args, capture_output=True, text=True, timeout=120, **kw)


def test_default_scene_writes_exr_png_and_stats(tmp_path):
    out = tmp_path / "d.exr"
    r = run(["-o", str(out), "--spp", "4", "--stats", str(tmp_path / "s.json"), *SMALL])
    assert r.returncode == 0, r.stderr
    rgb, var = mpg.read_exr(str(out))
    assert rgb.shape == (24, 32, 3) and var is not None
    assert np.isfinite(rgb).all() and rgb.mean() > 0
    assert (tmp_path / "d.png").exists()
    st = json.loads((tmp_path / "s.json").read_text())
    assert st["spp"] == 4 and st["integrator"] == "path" and st["rejected_samples"] == 0


def test_missing_scene_file_is_one_clear_line(tmp_path):
    r = run([str(tmp_path / "nope.xml")])
    assert r.returncode == 1
    assert "nope.xml: no such scene file" in r.stderr
    assert "Traceback" not in r.stderr


def test_malformed_xml_names_file_and_line(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text('<scene version="3.0.0">\n  <shape type="sphere">\n  </shap>\n</scene>\n')
    r = run([str(bad), "-o", str(tmp_path / "x.exr")])
    assert r.returncode == 1
    assert "bad.xml:3" in r.stderr
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "x.exr").exists()


def test_unknown_plugin_is_an_error(tmp_path):
    bad = tmp_path / "plug.xml"
    bad.write_text('<scene version="3.0.0">\n<shape type="teapot"/>\n</scene>\n')
    r = run([str(bad)])
    assert r.returncode == 1 and "plug.xml:2" in r.stderr and "teapot" in r.stderr


def test_bad_arguments():
    assert run(["--spp", "0"]).returncode == 1
    assert run(["-o", "x.png"]).returncode == 1
    assert run(["-D", "novalue"]).returncode == 2  # argparse usage error


def test_time_limit_writes_the_image(tmp_path):
    out = tmp_path / "t.exr"
    t0 = time.monotonic()
    r = run(["-o", str(out), "--time", "1.5", *SMALL])
    assert r.returncode == 0, r.stderr
    assert time.monotonic() - t0 < 20
    assert out.exists() and "time limit reached" in r.stderr


def test_ctrl_c_writes_what_it_has(tmp_path):
    out = tmp_path / "i.exr"
    p = subprocess.Popen(CLI + ["-o", str(out), "--spp", "1000000", "--stats",
                                str(tmp_path / "s.json"), "-D", "res_x=64", "-D", "res_y=48"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(4.0)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert "interrupted" in err
    rgb, _ = mpg.read_exr(str(out))
    assert np.isfinite(rgb).all()
    st = json.loads((tmp_path / "s.json").read_text())
    assert st["interrupted"] is True and st["spp"] >= 1


def test_integrator_parameters_on_the_command_line(tmp_path):
    st = tmp_path / "s.json"
    r = run(["--integrator", "sms", "-P", "tau=TT", "-P", "max_depth=6", "--spp", "1",
             "-o", str(tmp_path / "c.exr"), "--stats", str(st), *SMALL])
    assert r.returncode == 0, r.stderr
    s = json.loads(st.read_text())
    assert s["integrator"] == "sms" and s["integrator_params"]["tau"] == "TT"
    r = run(["--integrator", "sms", "-P", "tau=XY", "--spp", "1", "-o", str(tmp_path / "d.exr"), *SMALL])
    assert r.returncode == 1 and "tau" in r.stderr


def test_mpg_summary_names_handoff_all(tmp_path, scenes_dir):
    """With -P handoff_all=K the summary says every pixel was handed off, not
    the learned rates the render did not use."""
    scene = str(scenes_dir / "sphere_glass.xml")
    r = run([scene, "-D", "res=16", "--integrator", "mpg", "-P", "handoff_all=2", "--spp", "24",
             "-o", str(tmp_path / "m.exr"), "--chain-rate-map", str(tmp_path / "q.png")])
    assert r.returncode == 0, r.stderr
    assert "every pixel handed to the path tracer with 2 guided traces" in r.stderr
    assert "chain rates per pixel" not in r.stderr
    # (and the rate map it writes is the render's, 0 everywhere, with a note saying so)
    assert (tmp_path / "q.png").exists() and "chain rate map written is 0 everywhere" in r.stderr
    # handoff_all=auto names its choice and the model's ratio it rests on
    # (128 spp: enough training for the hand-off and the model of the traces)
    r = run([scene, "-D", "res=16", "--integrator", "mpg", "-P", "handoff_all=auto", "--spp", "128",
             "-o", str(tmp_path / "a.exr"), "--stats", str(tmp_path / "a.json")])
    assert r.returncode == 0, r.stderr
    st = json.loads((tmp_path / "a.json").read_text())
    assert st["handoff_all_mode"] == "auto" and "handoff_all=auto" in r.stderr
    assert f"{st['handoff_all_model_ratio']:.2g}x" in r.stderr
    # (either choice is named: "kept them" names the model of every pixel
    # handed off too, so the check is the choice's own phrase)
    assert ("every pixel handed to the path tracer" in r.stderr) == (st["handoff_all"] > 0)
    assert ("handoff_all=auto kept them" in r.stderr) == (st["handoff_all"] == 0)


def test_mpg_summary_and_chain_rate_map(tmp_path, scenes_dir):
    """mpg-render names what mpg learned and writes its per-pixel chain rates as
    a grey PNG (log2 scale: 1/32 black, 1 white); without learned rates it says
    so instead of writing a misleading picture."""
    from PIL import Image as PILImage

    png = tmp_path / "q.png"
    scene = str(scenes_dir / "sphere_glass.xml")
    r = run([scene, "-D", "res=16", "--integrator", "mpg", "--spp", "24", "-o", str(tmp_path / "m.exr"),
             "--chain-rate-map", str(png)])
    assert r.returncode == 0, r.stderr
    assert "mpg trained" in r.stderr and "chain rates per pixel" in r.stderr
    # (24 spp train 7: the hand-off waits for more, and the summary says so)
    assert "hand-off off: 7 training spp" in r.stderr
    # (and the render's own refinements of the pixel split: at 4, 8 and 16 of its 17 spp)
    assert "refined 3 times by the render's own samples" in r.stderr
    # a pixel split held under its cost cap says so
    rc = run([scene, "-D", "res=16", "--integrator", "mpg", "--spp", "24", "-P", "pixel_split_max_cost=1.03",
              "-o", str(tmp_path / "c.exr")])
    assert rc.returncode == 0, rc.stderr
    assert "pixels split (mse)" in rc.stderr and "capped at 1.03x" in rc.stderr
    g = np.asarray(PILImage.open(png))
    assert g.shape == (16, 16, 3) and len(np.unique(g)) > 1   # the rates differ across the image
    png2 = tmp_path / "q2.png"
    r = run([scene, "-D", "res=16", "--integrator", "path", "--spp", "2", "-o", str(tmp_path / "p.exr"),
             "--chain-rate-map", str(png2)])
    assert r.returncode == 0 and "no learned chain rates" in r.stderr and not png2.exists()


def test_sampler_on_the_command_line(tmp_path):
    st = tmp_path / "s.json"
    r = run(["--sampler", "stratified", "--spp", "2", "-o", str(tmp_path / "s.exr"), "--stats", str(st),
             *SMALL])
    assert r.returncode == 0, r.stderr
    assert json.loads(st.read_text())["sampler"] == "stratified"
    r = run(["--sampler", "sobol", "--spp", "1", "-o", str(tmp_path / "t.exr"), *SMALL])
    assert r.returncode == 2 and "--sampler" in r.stderr
