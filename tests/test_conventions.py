"""Conventions a user meets first: the plot functions draw into given Axes (`ax=`) or a given Figure
(`fig=`) and return the Figure; `Solution.to_xarray` mirrors `Solution.to_dataframe`.

The figures are drawn with fake fit results (only the attributes the plots read), so no fit runs; one
small simulation of the variator is shared by the xarray tests.
"""

import dataclasses
import sys
import types
from typing import Any

import numpy as np
import pytest


# --- plots: ax= and fig= ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def mpl():
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    yield plt
    plt.close("all")


def fake_fit(observe=("phi1", "phi2"), n=21) -> Any:
    """What `plot_fit` and `plot_ratio` read from a FitResult, with made-up numbers."""
    t = np.linspace(0.0, 2.0, n)
    measured = np.stack([np.sin(t + i) for i in range(len(observe))], axis=1)
    knots = np.linspace(0.0, 2.0, 4)
    return types.SimpleNamespace(
        observe=tuple(observe),
        t=t,
        measured=measured,
        fitted=measured + 1e-3,
        residuals=np.full_like(measured, -1e-3),
        noise={c: 1e-3 for c in observe},
        rms_by_channel={c: 1e-3 for c in observe},
        params={"U21": types.SimpleNamespace(knots=knots)},
        estimates={"U21": {"value": 1.0 + 0.1 * knots, "std": np.full(4, 0.01)}},
        profile_band=lambda name, ts: (1.0 + 0.1 * ts, np.full_like(ts, 0.01)),
    )


def fake_record(n=21):
    t = np.linspace(0.0, 2.0, n)
    return types.SimpleNamespace(t=t, inputs={"M1": np.cos(t)})


def test_plot_fit_draws_into_the_given_axes_and_returns_their_figure(mpl):
    from jaxnh.identify.plots import plot_fit

    backend = mpl.get_backend()
    fig, axs = mpl.subplots(4, 1)  # the coordinates, 2 residual panels, the inputs
    open_figures = mpl.get_fignums()
    out = plot_fit(fake_fit(), fake_record(), ax=axs, title="given axes")
    assert out is fig
    assert mpl.get_fignums() == open_figures  # no figure of its own
    assert all(a.lines for a in axs)
    assert axs[0].get_title() == "given axes" and axs[-1].get_xlabel() == "t [s]"
    assert mpl.get_backend() == backend
    # a list of Axes, without a record: one panel fewer
    fig3, axs3 = mpl.subplots(3, 1)
    assert plot_fit(fake_fit(), ax=list(axs3)) is fig3 and all(a.lines for a in axs3)
    mpl.close(fig)
    mpl.close(fig3)


def test_plot_fit_ax_is_checked(mpl):
    from matplotlib.figure import Figure

    from jaxnh.identify.plots import plot_fit

    fig, axs = mpl.subplots(3, 1)
    with pytest.raises(ValueError, match="ax= must be 4 Axes"):
        plot_fit(fake_fit(), fake_record(), ax=axs)
    with pytest.raises(ValueError, match="not both"):
        plot_fit(fake_fit(), ax=axs, fig=Figure())
    other = Figure().subplots(1, 1)
    with pytest.raises(ValueError, match="one Figure"):
        plot_fit(fake_fit(), ax=[axs[0], axs[1], other])
    not_axes: Any = [axs[0], axs[1], "not an axes"]
    with pytest.raises(TypeError, match="matplotlib Axes"):
        plot_fit(fake_fit(), ax=not_axes)
    mpl.close(fig)


def test_plot_fit_with_fig_still_clears_and_fills_it(mpl):
    from matplotlib.figure import Figure

    from jaxnh.identify.plots import plot_fit

    fig = Figure()
    fig.subplots(2, 2)  # cleared
    assert plot_fit(fake_fit(), fake_record(), fig=fig) is fig and len(fig.axes) == 4
    new = plot_fit(fake_fit())  # neither: a new pyplot figure
    assert len(new.axes) == 3
    mpl.close(new)


def test_plot_ratio_ax_and_fig(mpl):
    from matplotlib.figure import Figure

    from jaxnh.identify.plots import plot_ratio

    truth = lambda t: 1.0 + 0.1 * t
    fig = Figure()
    axs = fig.subplots(1, 2)  # any arrangement: the profile, then the deviations
    assert plot_ratio(fake_fit(), truth, n=11, ax=axs) is fig
    assert axs[0].get_title() == "transmission ratio U21(t)" and axs[1].get_ylabel() == "U21 deviation"
    with pytest.raises(ValueError, match="ax= must be 2 Axes"):
        plot_ratio(fake_fit(), ax=axs[:1])
    fig2 = Figure()
    assert plot_ratio(fake_fit(), truth, n=11, fig=fig2) is fig2 and len(fig2.axes) == 2
    # Axes of a SubFigure: the Figure that holds them (the one to save) is returned
    root = Figure()
    subs: Any = root.subfigures(1, 2)
    sub = subs[1]
    assert plot_ratio(fake_fit(), n=11, ax=sub.subplots(2, 1)) is root


# --- Solution.to_xarray --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sol():
    import jax.numpy as jnp

    import jaxnh as nh
    from jaxnh.models import variator as V

    p = V.default_params()
    ts = jnp.linspace(0.0, 1.0, 11)
    qd0 = jnp.array([2.0, 2.0 * float(p.U21(0.0))])
    return nh.simulate(V.mechanism(), p, jnp.zeros(2), qd0, ts, record=("multipliers", "energy", "residual"))


def test_to_xarray_holds_the_solution(sol):
    pytest.importorskip("xarray")
    ds = sol.to_xarray()
    assert ds.sizes == {"t": 11, "coordinate": 2, "constraint": 1}
    assert list(ds["coordinate"].values) == list(sol.names) == ["phi1", "phi2"]
    np.testing.assert_array_equal(ds["t"].values, np.asarray(sol.ts))
    for name in ("q", "qd", "multipliers", "energy", "residual"):
        np.testing.assert_array_equal(ds[name].values, np.asarray(getattr(sol, name)), err_msg=name)
    assert ds["q"].dims == ("t", "coordinate") and ds["multipliers"].dims == ("t", "constraint")
    np.testing.assert_array_equal(ds["qd"].sel(coordinate="phi2").values, np.asarray(sol.qd[:, 1]))
    assert ds["t"].attrs["units"] == "s" and ds["energy"].attrs["units"] == "J"
    assert all("units" in ds[v].attrs for v in ("q", "qd", "multipliers", "residual"))
    assert bool(ds["success"]) and ds.attrs["message"] == sol.message == "success"


def test_to_xarray_leaves_out_what_was_not_recorded(sol):
    pytest.importorskip("xarray")
    ds = sol.to_xarray()
    ds_q = dataclasses.replace(sol, multipliers=None, residual=None).to_xarray()
    assert set(ds_q.data_vars) == {"q", "qd", "energy", "success"} and "constraint" not in ds_q.dims
    np.testing.assert_array_equal(ds_q["q"].values, ds["q"].values)


def test_to_xarray_of_a_batch(sol):
    pytest.importorskip("xarray")
    import jax

    batch = jax.tree_util.tree_map(lambda x: np.stack([x, x, x]), sol)  # as jax.vmap returns it
    ds = batch.to_xarray()
    assert ds["q"].dims == ("batch", "t", "coordinate") and ds.sizes["batch"] == 3
    assert ds.attrs["batch_shape"] == [3] and ds["success"].values.tolist() == [True] * 3
    np.testing.assert_array_equal(ds["energy"].values, np.asarray(batch.energy))
    np.testing.assert_array_equal(ds["t"].values, np.asarray(sol.ts))
    # elements reported at different times (an event stopped one early) share no time axis
    ts = np.asarray(batch.ts).copy()
    ts[1, -3:] = np.inf
    with pytest.raises(ValueError, match="different times"):
        dataclasses.replace(batch, ts=ts).to_xarray()


def test_to_xarray_without_xarray_names_the_extra(sol, monkeypatch):
    monkeypatch.setitem(sys.modules, "xarray", None)  # import xarray → ImportError
    with pytest.raises(ImportError, match=r"needs xarray.*jaxnh\[data\]"):
        sol.to_xarray()
