"""PySINDy fitting omega' = f(omega, dP, sign(omega), 1) on a recording (STLSQ, smoothed finite differences): the
peer of `hydrolens analyze`. Prints the median time of REPEATS fits (CSV load excluded, timed apart) and the
equation found: `pysindy_fit rows=N load_s=… fit_s=… terms=… equation="…"`.

For the reference plant the true coefficients are, in omega' [rad/s^2]: dP [bar] 6.37 (D_m/J), omega -0.5 (B/J),
load [N·m] -12.5 (1/J). Without the load among the inputs (the brief's candidate set) the brake steps are an
omitted variable that dP balances in steady state; a second fit adds the recording's load_nm column.

usage: pysindy_fit.py REC.csv [REPEATS]
"""

import statistics
import sys
import time
import warnings

import numpy as np
import pysindy as ps


def load(path):
    with open(path) as f:
        header = f.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    col = {name: i for i, name in enumerate(header)}
    t = data[:, col["t_s"]]
    dp = data[:, col["p_in_bar"]] - data[:, col["p_out_bar"]]
    omega = data[:, col["omega_rad_s"]]
    load_nm = data[:, col["load_nm"]] if "load_nm" in col else None
    return t, omega, dp, load_nm


def model(inputs):
    # omega and the inputs as they are, sign(omega) from omega only, and a constant
    identity = ps.CustomLibrary(library_functions=[lambda z: z], function_names=[lambda s: s])
    sign = ps.CustomLibrary(
        library_functions=[lambda z: np.sign(z)], function_names=[lambda s: f"sign({s})"], include_bias=True
    )
    library = ps.GeneralizedLibrary([identity, sign], inputs_per_library=[list(range(inputs + 1)), [0]])
    return ps.SINDy(
        optimizer=ps.STLSQ(threshold=0.1),
        feature_library=library,
        differentiation_method=ps.SmoothedFiniteDifference(),
    )


def main():
    path = sys.argv[1]
    repeats = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    t0 = time.perf_counter()
    t, omega, dp, load_nm = load(path)
    load_s = time.perf_counter() - t0
    # the candidate terms of the brief, then the same with the measured load torque as a further input
    variants = [("dP", dp.reshape(-1, 1), ["omega", "dP"])]
    if load_nm is not None:
        variants.append(("dP+load", np.column_stack([dp, load_nm]), ["omega", "dP", "load"]))
    for label, u, names in variants:
        fits = []
        m = None
        for _ in range(repeats):
            m = model(u.shape[1])
            start = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                m.fit(omega.reshape(-1, 1), t=t, u=u, feature_names=names)
            fits.append(time.perf_counter() - start)
        coef = m.coefficients()[0]
        terms = [(n, c) for n, c in zip(m.get_feature_names(), coef) if c != 0.0]
        equation = " + ".join(f"{c:.3f} {n}" for n, c in terms).replace("+ -", "- ")
        print(
            f"pysindy_fit inputs={label} rows={len(t)} load_s={load_s:.3f} fit_s={statistics.median(fits):.3f} "
            f'terms={len(terms)} equation="omega\' = {equation}"'
        )


if __name__ == "__main__":
    main()
