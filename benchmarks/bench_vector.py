"""Papers 003 (online ellipsoid calibration) and 000 (21-parameter component compensation):
their simulations re-run, the paper's figures next to ours.

    .venv/bin/python benchmarks/bench_vector.py

Exits non-zero when a figure the papers claim does not hold here (prior initialisation not
2x faster, magnitude error above 1.2x noise, roll error above 1 deg, scaled-H filter not
within 2 % by 4000 samples or total-field error above 7 nT, fuzzy R not better than fixed R
under time-varying noise).
"""

from __future__ import annotations

import sys
import time

import numpy as np
from report import finish

from pipeline.geo.frames import ned_to_body
from pipeline.simulate.vector_carriers import (
    PAPER_000,
    PAPER_003_FIELD_G,
    rotating_carrier,
    spinning_carrier,
)
from pipeline.vector.component import ComponentKF, batch_fit, convergence_sample
from pipeline.vector.ellipsoid import (
    Ellipsoid,
    EllipsoidKF,
    angle_error_deg,
    convergence_time,
    fit_ellipsoid,
    magnitude_error,
    roll_from_radial,
    running_rms,
)
from pipeline.vector.fuzzy import RorFuzzy

SIGMA_G = 0.0005


def paper_003() -> tuple[list[tuple], list[str]]:
    fl = spinning_carrier(seed=1)
    # an earlier calibration of the same carrier whose hard iron has since moved by ~8 mG
    prior_fl = spinning_carrier(
        seed=7,
        duration_s=2.0,
        pitch_from_deg=30.0,
        pitch_to_deg=-30.0,
        spin_rev_s=3.0,
        hard_iron_G=(0.052, -0.028, 0.052),
    )
    prior = fit_ellipsoid(prior_fl.measured_G, PAPER_003_FIELD_G, SIGMA_G)
    res = {}
    for name, kf in (
        ("naive", EllipsoidKF.naive(PAPER_003_FIELD_G, SIGMA_G)),
        ("prior", EllipsoidKF.from_prior(prior, SIGMA_G)),
    ):
        st = kf.run(fl.measured_G)
        # scored with the state before each sample's update (after it, the sample is fitted)
        err = magnitude_error(kf.states_before, fl.measured_G, PAPER_003_FIELD_G)
        conv = convergence_time(fl.time_s, running_rms(err, 25), 2 * SIGMA_G, 0.5)
        final = kf.ellipsoid()
        tail = np.linalg.norm(final.calibrate(fl.measured_G[-500:]), axis=1) - PAPER_003_FIELD_G
        hard = np.array(
            [
                np.linalg.norm(Ellipsoid(x, PAPER_003_FIELD_G).centre - fl.hard_iron_G)
                for x in st[:250]
            ]
        )
        early = (float(hard[0]), float(np.max(hard)))
        res[name] = (conv, early, float(np.sqrt(np.mean(tail**2))) / SIGMA_G, final, kf.min_eig)
    n = fl.time_s.size
    unrolled = ned_to_body(np.tile(fl.field_ned_G, (n, 1)), np.zeros(n), fl.pitch_deg, np.zeros(n))
    raw = angle_error_deg(roll_from_radial(fl.measured_G, unrolled), fl.roll_deg)
    cal = angle_error_deg(
        roll_from_radial(res["prior"][3].calibrate(fl.measured_G), unrolled), fl.roll_deg
    )
    nv, pr = res["naive"], res["prior"]
    ok = nv[0] is not None and pr[0] is not None and pr[0] > 0
    ratio = nv[0] / pr[0] if ok else float("nan")
    rows = [
        (
            "003",
            "convergence, naive start (s; state before each update)",
            "~3",
            f"{nv[0]}" if nv[0] is None else f"{nv[0]:.2f}",
            "",
        ),
        (
            "003",
            "convergence, prior-fit start (s; state before each update)",
            "~1",
            f"{pr[0]}" if pr[0] is None else f"{pr[0]:.2f}",
            "",
        ),
        ("003", "speed-up prior vs naive", "~2x", f"{ratio:.1f}x", ""),
        (
            "003",
            "hard-iron error: first sample -> largest in the first 0.5 s, naive (G)",
            "naive diverges early",
            f"{nv[1][0]:.4f} -> {nv[1][1]:.3g}",
            "",
        ),
        (
            "003",
            "hard-iron error: first sample -> largest in the first 0.5 s, prior (G)",
            "no divergence",
            f"{pr[1][0]:.4f} -> {pr[1][1]:.4f}",
            "",
        ),
        ("003", "magnitude error after calibration / noise", "-", f"{pr[2]:.2f}", ""),
        (
            "003",
            "roll error before: mean / std / max (deg)",
            "0.547 / 5.59 / <=8",
            f"{raw.mean():.3f} / {raw.std():.2f} / {np.abs(raw).max():.1f}",
            "",
        ),
        (
            "003",
            "roll error after: mean / std / 99th pct (deg)",
            "-0.251 / 0.367 / <1",
            f"{cal.mean():.3f} / {cal.std():.3f} / {np.percentile(np.abs(cal), 99):.2f}",
            f"{cal.std() / 0.367:.2f}",
        ),
    ]
    errors = []
    if not (ok and ratio >= 2):  # a prior start "converged" at 0 s is a scoring error
        errors.append(f"prior start not 2x faster ({pr[0]} vs {nv[0]} s)")
    if not nv[1][1] > 10 * nv[1][0] or pr[1][1] > 1.5 * pr[1][0]:
        errors.append("naive start did not diverge early, or the prior start did")
    if pr[2] > 1.2:
        errors.append(f"magnitude error {pr[2]:.2f} x noise > 1.2")
    if np.percentile(np.abs(cal), 99) > 1.0:
        errors.append("roll error above 1 deg")
    return rows, errors


def paper_000() -> tuple[list[tuple], list[str]]:
    fl = rotating_carrier()
    truth = PAPER_000.state(True)
    rows, errors = [], []
    raw_tot = np.linalg.norm(fl.measured_nT, axis=1) - np.linalg.norm(fl.earth_nT, axis=1)
    raw_cmp = np.sqrt(np.mean((fl.measured_nT - fl.earth_nT) ** 2, axis=0))
    rows.append(
        (
            "000",
            "total-field error before (nT)",
            "175.75",
            f"{np.sqrt(np.mean(raw_tot**2)):.1f}",
            "",
        )
    )
    rows.append(
        (
            "000",
            "X / Y / Z error before (nT)",
            "59.20 / 110.20 / 122.20",
            " / ".join(f"{v:.1f}" for v in raw_cmp),
            "",
        )
    )
    for label, kf in (
        ("KF, original H", ComponentKF.paper(scaled=False)),
        ("KF, scaled H", ComponentKF.paper(scaled=True)),
    ):
        t0 = time.perf_counter()
        p = kf.run(fl.earth_nT, fl.earth_rate_nT_s, fl.measured_nT)
        dt = time.perf_counter() - t0
        rel = np.abs(p.state(True) - truth) / np.abs(truth)
        comp = p.compensate(fl.measured_nT, fl.earth_rate_nT_s)
        tot = np.linalg.norm(comp, axis=1) - np.linalg.norm(fl.earth_nT, axis=1)
        cmp_ = np.sqrt(np.mean((comp - fl.earth_nT) ** 2, axis=0))
        conv = convergence_sample(kf.history.states, truth, 0.02)
        perm = p.permanent_nT
        tot_rms = float(np.sqrt(np.mean(tot**2)))
        rows += [
            (
                "000",
                f"{label}: permanent T_p (nT; truth 40 / -100 / 120)",
                "-",
                " / ".join(f"{v:.1f}" for v in perm),
                "",
            ),
            ("000", f"{label}: largest parameter error", "<= ~2 %", f"{100 * rel.max():.2f} %", ""),
            (
                "000",
                f"{label}: converged (RMS parameter error <= 2 %) at sample",
                "~4000",
                str(conv),
                f"{conv / 4000:.2f}",
            ),
            # the paper's 6.6585 nT is its fuzzy-R run, which in its configuration
            # (R = 1e-3 nT^2) is the fixed-R filter: R sits on its clamp from sample
            # ~110 (benchmarks/bench_fuzzy_r.py, docs/science-paper000.md)
            (
                "000",
                f"{label}, fixed R: total-field error after (nT)",
                "6.6585 (fuzzy R = fixed R there)",
                f"{tot_rms:.2f}",
                f"{tot_rms / 6.6585:.2f}",
            ),
            (
                "000",
                f"{label}: X / Y / Z error after (nT)",
                "6.03 / 1.72 / 1.52",
                " / ".join(f"{v:.2f}" for v in cmp_),
                "",
            ),
            ("000", f"{label}: 10 000 steps (s)", "-", f"{dt:.2f}", ""),
        ]
        if label.endswith("scaled H"):
            if conv > 4000 or rel.max() > 0.02 or tot_rms > 7.0:
                errors.append(
                    f"scaled KF: converged {conv}, max error {rel.max():.3f}, "
                    f"total {tot_rms:.2f} nT"
                )
        elif np.max(np.abs(perm)) > 10.0:
            errors.append("original-H KF moved the permanent terms (the paper's point)")
    p, resid, _ = batch_fit(fl.earth_nT, fl.earth_rate_nT_s, fl.measured_nT)
    rel = np.abs(p.state(True) - truth) / np.abs(truth)
    comp = p.compensate(fl.measured_nT, fl.earth_rate_nT_s)
    tot = np.linalg.norm(comp, axis=1) - np.linalg.norm(fl.earth_nT, axis=1)
    rows += [
        ("000", "batch LS: largest parameter error", "-", f"{100 * rel.max():.2f} %", ""),
        (
            "000",
            "batch LS: total-field error after (nT)",
            "-",
            f"{np.sqrt(np.mean(tot**2)):.2f}",
            "",
        ),
    ]
    # time-varying noise: 5 nT, then 60 nT for 3000 samples, then 5 nT again
    sig = np.full(10_000, 5.0)
    sig[3000:6000] = 60.0
    wins = 0
    for seed in (1, 2, 3):
        fl2 = rotating_carrier(noise_nT=sig, seed=seed)
        errs = {}
        for name, fz in (("fixed R", None), ("fuzzy R", RorFuzzy())):
            kf = ComponentKF(
                ComponentKF.paper().x0,
                100 * np.eye(21),
                1e-12 * np.eye(21),
                25.0 * np.eye(3),
                True,
                fz,
            )
            pp = kf.run(fl2.earth_nT, fl2.earth_rate_nT_s, fl2.measured_nT)
            errs[name] = float(np.sqrt(np.mean(((pp.state(True) - truth) / truth) ** 2)))
        pb, _, _ = batch_fit(fl2.earth_nT, fl2.earth_rate_nT_s, fl2.measured_nT)
        errs["batch LS"] = float(np.sqrt(np.mean(((pb.state(True) - truth) / truth) ** 2)))
        wins += errs["fuzzy R"] < errs["fixed R"]
        rows.append(
            (
                "000",
                f"noise 5 -> 60 -> 5 nT, seed {seed}: RMS parameter error "
                "fixed R / fuzzy R / batch",
                "fuzzy better",
                " / ".join(f"{100 * errs[k]:.3f} %" for k in ("fixed R", "fuzzy R", "batch LS")),
                f"{errs['fuzzy R'] / errs['fixed R']:.2f}",
            )
        )
    if wins < 3:
        errors.append(f"fuzzy R better than fixed R on {wins} of 3 seeds")
    return rows, errors


def main() -> int:
    rows3, e3 = paper_003()
    rows0, e0 = paper_000()
    print("| paper | figure | paper | ours | ratio |\n|---|---|---|---|---|")
    for r in rows3 + rows0:
        print("| " + " | ".join(r) + " |")
    print()
    return finish([("papers", "003, 000")], e3 + e0)


if __name__ == "__main__":
    sys.exit(main())
