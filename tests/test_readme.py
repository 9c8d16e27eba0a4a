"""The README's worked example runs as printed and gives the closed-form answer."""

import pathlib
import re

import numpy as np

from jaxnh.models import variator as V
from jaxnh.profiles import Fourier


README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_readme_example_matches_closed_form(capsys):
    code = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)[0]
    env = {}
    exec(compile(code, str(README), "exec"), env)
    sol = env["sol"]
    assert sol.message == "success"
    p = V.VariatorParams(J1=0.02, J2=0.05, U21=Fourier(1.0, sin=[0.4], period=2.0), M1=0.3, M2=-0.1)
    q_ref, qd_ref = V.closed_form(p, env["ts"], w0=2.0)
    # default tolerances rtol=1e-8, atol=1e-10 over 10 s: global error well below 1e-5 rad
    np.testing.assert_allclose(sol.q, q_ref, atol=1e-5, rtol=1e-7)
    # the multiplier printed is the paper's lambda = M2 - J2 (U21' phi1' + U21 phi1'')
    w = sol.qd[-1, 0]
    a = V.paper_eq9(w, env["ts"][-1], p)
    np.testing.assert_allclose(sol.multipliers[-1, 0], V.paper_multiplier(w, a, env["ts"][-1], p), rtol=1e-9)
    assert "success" in capsys.readouterr().out
