"""PySINDy fitting the speed equation omega' = f(...) on a recording (STLSQ, smoothed finite differences): the peer of
`hydrolens analyze`. For each variant prints the median time of REPEATS fits (CSV load excluded, timed apart), the
equation found, and the physical parameters it implies, in the names of `hydrolens analyze --json`:

    pysindy_fit inputs=… rows=N load_s=… fit_s=… terms=… J=… B=… Dm_cm3=… Tc=… Toff=… found="…" equation="…"

Candidate terms: the ones `hydrolens analyze` fits in its torque balance that SINDy can write as a library over
(omega, dP, load): omega, dP, the measured load torque, sign(omega), a constant. With

    omega' = a·dP + b·omega + c·T_L + d·sign(omega) + e          (dP in bar, T_L in N·m)

and the plant's J omega' = D_m·1e5·dP − B omega − T_L − T_c sgn(omega) − T_off (PHYSICS.md):

    J = −1/c,  B = −b·J,  D_m = a·J/1e5 [m³/rad] (displacement_cm3 = D_m·2π·1e6),  T_c = −d·J,  T_off = −e·J.

Without the load among the inputs (variant "dP", the candidate set of the issue) c does not exist and J is taken
from a and the nominal D_m (32 cm³, as `analyze` takes D_m as given): J = D_m·1e5/a.

What SINDy cannot express with this library, and `analyze` tries: a dead time (f_cmd(t − τ) is not a function of
the current state and inputs; it would need lagged copies of the setpoint and a model of the drive), entrained air
and internal leakage / motor slip (they live in the pressure equation, whose pump flow needs the drive's ramp limit,
a clip, and whose derivative at σ = 0.3 bar and 1 kHz is mostly noise), Stribeck friction (exp(−(ω/ω_s)²) has an
unknown ω_s inside: a grid of ω_s values would be needed). SINDy's sign(omega) is of the measured (noisy) speed;
the plant's is tanh(omega/0.05). SINDy fits the whole recording; `analyze` fits the first 70 % and judges on the rest.

usage: pysindy_fit.py REC.csv [REPEATS] [--only dP|dP+load]
"""

import math
import statistics
import sys
import time
import warnings

import numpy as np
import pysindy as ps

NOMINAL_DM_M3_RAD = 32.0e-6 / (2.0 * math.pi)


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


def physical(coef_by_name):
    """The plant's parameters from omega' = a dP + b omega + c load + d sign(omega) + e (absent terms are 0)."""
    a = coef_by_name.get("dP", 0.0)
    b = coef_by_name.get("omega", 0.0)
    c = coef_by_name.get("load")
    d = coef_by_name.get("sign(omega)", 0.0)
    e = coef_by_name.get("1", 0.0)
    if c is not None:
        j = -1.0 / c if c != 0.0 else math.nan
    else:
        j = NOMINAL_DM_M3_RAD * 1e5 / a if a != 0.0 else math.nan
    # + 0.0 turns −0.0 (an absent term times −J) into 0
    return {
        "J": j,
        "B": -b * j + 0.0,
        "Dm_cm3": a * j / 1e5 * 2.0 * math.pi * 1e6 + 0.0,
        "Tc": -d * j + 0.0,
        "Toff": -e * j + 0.0,
    }


def found(p, with_load):
    """What the fit says in the words of `analyze`: the parameters, and the extra terms it kept."""
    parts = [f"J {p['J']:.4g}" + ("" if with_load else " (from D_m nominal)"), f"B {p['B']:.4g}"]
    if with_load:
        parts.append(f"D_m {p['Dm_cm3']:.3g} cm³")
    if p["Tc"] != 0.0:
        parts.append(f"sign(ω) term ≙ coulomb_friction {p['Tc']:.3g} N·m")
    if p["Toff"] != 0.0:
        parts.append(f"constant ≙ torque_offset {p['Toff']:.3g} N·m")
    if p["Tc"] == 0.0 and p["Toff"] == 0.0:
        parts.append("no friction or offset term")
    return ", ".join(parts)


def main():
    args = sys.argv[1:]
    only = None
    if "--only" in args:
        i = args.index("--only")
        only = args[i + 1]
        del args[i : i + 2]
    path = args[0]
    repeats = int(args[1]) if len(args) > 1 else 3
    t0 = time.perf_counter()
    t, omega, dp, load_nm = load(path)
    load_s = time.perf_counter() - t0
    # the candidate terms of the issue, then the same with the measured load torque as a further input
    variants = [("dP", dp.reshape(-1, 1), ["omega", "dP"])]
    if load_nm is not None:
        variants.append(("dP+load", np.column_stack([dp, load_nm]), ["omega", "dP", "load"]))
    for label, u, names in variants:
        if only is not None and label != only:
            continue
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
        terms = [(n, float(c)) for n, c in zip(m.get_feature_names(), coef) if c != 0.0]
        equation = " + ".join(f"{c:.3f} {n}" for n, c in terms).replace("+ -", "- ")
        p = physical(dict(terms))
        params = " ".join(f"{k}={v:.4g}" for k, v in p.items())
        print(
            f"pysindy_fit inputs={label} rows={len(t)} load_s={load_s:.3f} fit_s={statistics.median(fits):.3f} "
            f'terms={len(terms)} {params} found="{found(p, "load" in names)}" equation="omega\' = {equation}"',
            flush=True,
        )


if __name__ == "__main__":
    main()
