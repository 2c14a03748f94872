"""drivectl.profiles: ptp (ruckig), circle, dwell, sequence, TOML library, check_limits."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import ruckig

from drivectl.profiles import (
    Circle,
    Dwell,
    PointToPoint,
    Profile,
    ProfileError,
    Sequence,
    back_and_forth,
    check_limits,
    list_profiles,
    load_profile,
)

TOL = 1e-9
LIBRARY = ["back-and-forth", "circle", "fingerprint", "seed-000", "short-move"]


def seed000() -> PointToPoint:
    return PointToPoint(0.0, 0.065, 0.1, 1.0, 40.0, hold_until=2.5, name="seed-000")


def ptp_cases() -> list[PointToPoint]:
    """Moves that reach vmax, that do not (short), that do not reach amax, and negative ones with t0."""
    return [
        seed000(),
        PointToPoint(0.0, 0.002, 0.1, 1.0, 40.0),  # too short to reach vmax
        PointToPoint(0.0, 0.0001, 0.1, 1.0, 40.0),  # too short to reach amax
        PointToPoint(0.03, -0.02, 0.05, 0.5, 20.0, t0=0.4, hold_until=1.0),
        PointToPoint(-0.01, 0.04, 0.2, 3.0, 500.0, t0=0.1),
    ]


def random_times(profile: Profile, n: int = 400, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(-0.5, profile.duration + 0.5, n)


# ---------------------------------------------------------------------------------------------- ptp
def test_seed000_move_time_and_end_state() -> None:
    p = seed000()
    assert p.move_time == pytest.approx(0.775, abs=1e-12)
    assert p.duration == 2.5
    assert p.start_position == 0.0
    for t in (0.775, 1.0, 2.5, 3.0):
        r = p.at(t)
        assert r.position == 0.065 and r.velocity == 0.0 and r.acceleration == 0.0 and r.jerk == 0.0
    r = p.at(0.775 - 1e-6)
    assert r.position == pytest.approx(0.065, abs=1e-12) and abs(r.velocity) < 1e-9
    assert p.at(-1.0).position == 0.0
    assert p.phase_times == pytest.approx([0, 0.025, 0.1, 0.125, 0.65, 0.675, 0.75, 0.775])


def test_ptp_duration_without_hold_and_with_short_hold() -> None:
    assert PointToPoint(0.0, 0.065, 0.1, 1.0, 40.0).duration == pytest.approx(0.775)
    assert PointToPoint(0.0, 0.065, 0.1, 1.0, 40.0, t0=0.5).duration == pytest.approx(1.275)
    # hold_until before the end of the move does not cut it short
    assert PointToPoint(0.0, 0.065, 0.1, 1.0, 40.0, hold_until=0.5).duration == pytest.approx(0.775)


def test_ptp_holds_before_t0() -> None:
    p = PointToPoint(0.01, 0.02, 0.1, 1.0, 40.0, t0=0.3)
    pos, vel, acc, jerk = p.sample(np.array([-1.0, 0.0, 0.15, 0.3]))
    assert np.all(pos == 0.01) and not vel.any() and not acc.any()
    assert jerk[-1] == 40.0 and not jerk[:-1].any()  # the move starts exactly at t0 with +jmax


@pytest.mark.parametrize("p", ptp_cases(), ids=lambda p: f"{p.start}->{p.target}")
def test_ptp_sample_equals_at_and_ruckig(p: PointToPoint) -> None:
    t = np.concatenate((random_times(p), p.phase_times))
    pos, vel, acc, jerk = p.sample(t)
    for i, ti in enumerate(t):
        r = p.at(float(ti))
        assert (r.position, r.velocity, r.acceleration, r.jerk) == (pos[i], vel[i], acc[i], jerk[i])

    # The piecewise-cubic evaluation agrees with ruckig's own Trajectory.at_time inside the move.
    otg, inp, traj = ruckig.Ruckig(1), ruckig.InputParameter(1), ruckig.Trajectory(1)
    inp.current_position, inp.target_position = [p.start], [p.target]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [p.vmax], [p.amax], [p.jmax]
    assert otg.calculate(inp, traj) == ruckig.Result.Working
    inside = (t >= p.t0) & (t <= p.t0 + p.move_time)
    assert inside.sum() > 10
    for ti, pi, vi, ai in zip(t[inside], pos[inside], vel[inside], acc[inside], strict=True):
        rp, rv, ra = (x[0] for x in traj.at_time(float(ti - p.t0)))
        assert pi == pytest.approx(rp, abs=1e-12)
        assert vi == pytest.approx(rv, abs=1e-12)
        assert ai == pytest.approx(ra, abs=1e-9)


@pytest.mark.parametrize("p", ptp_cases(), ids=lambda p: f"{p.start}->{p.target}")
def test_ptp_respects_limits_and_reaches_target(p: PointToPoint) -> None:
    t = np.linspace(-0.1, p.duration + 0.1, 50_001)
    pos, vel, acc, jerk = p.sample(t)
    assert np.abs(vel).max() <= p.vmax + TOL
    assert np.abs(acc).max() <= p.amax + TOL
    assert np.abs(jerk).max() <= p.jmax + TOL
    lo, hi = sorted((p.start, p.target))
    assert pos.min() >= lo - TOL and pos.max() <= hi + TOL  # no overshoot
    assert pos[-1] == p.target and vel[-1] == 0.0
    # check_limits agrees: the move planned right at its limits passes
    check_limits(p, position=(lo, hi), vmax=p.vmax, amax=p.amax)


@pytest.mark.parametrize("p", ptp_cases(), ids=lambda p: f"{p.start}->{p.target}")
def test_ptp_numeric_derivatives(p: PointToPoint) -> None:
    dt = 1e-5
    t = np.arange(-0.05, p.duration + 0.05, dt)
    pos, vel, acc, jerk = p.sample(t)
    # Central differences: pos is C2, vel C1 (acc continuous), acc only piecewise linear (jerk steps).
    assert np.abs(np.gradient(pos, dt) - vel).max() < 1e-7 * p.vmax + 1e-9 * p.jmax
    assert np.abs(np.gradient(vel, dt) - acc).max() < 2 * p.jmax * dt
    bounds = p.phase_times
    away = np.min(np.abs(t[:, None] - bounds[None, :]), axis=1) > 2 * dt
    assert np.abs(np.gradient(acc, dt) - jerk)[away].max() < 1e-6 * p.jmax


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"vmax": -1}, "profile seed-000: vmax: must be > 0, got -1"),
        ({"vmax": 0.0}, "profile seed-000: vmax: must be > 0, got 0.0"),
        ({"amax": math.inf}, "profile seed-000: amax: must be finite, got inf"),
        ({"jmax": math.nan}, "profile seed-000: jmax: must be finite, got nan"),
        ({"jmax": "40"}, "profile seed-000: jmax: must be a number, got '40'"),
        ({"target": math.nan}, "profile seed-000: target: must be finite, got nan"),
        ({"t0": -0.1}, "profile seed-000: t0: must be >= 0, got -0.1"),
    ],
)
def test_ptp_rejects_bad_arguments(kwargs: dict, message: str) -> None:
    args = {"start": 0.0, "target": 0.065, "vmax": 0.1, "amax": 1.0, "jmax": 40.0} | kwargs
    with pytest.raises(ProfileError) as exc:
        PointToPoint(**args, name="seed-000")
    assert str(exc.value) == message
    assert isinstance(exc.value, ValueError)


def test_zero_length_move_holds() -> None:
    p = PointToPoint(0.02, 0.02, 0.1, 1.0, 40.0, hold_until=0.2)
    assert p.move_time == 0.0 and p.duration == 0.2
    pos, vel, _, _ = p.sample(np.linspace(-1, 1, 11))
    assert np.all(pos == 0.02) and not vel.any()


# ------------------------------------------------------------------------------------------- circle
def test_circle_paper004_eq25() -> None:
    w = math.pi / 5
    x, y = Circle("x"), Circle("y")
    assert x.duration == 10.0 and x.omega == pytest.approx(w)
    assert x.start_position == pytest.approx(0.04) and y.start_position == pytest.approx(0.0)
    rx, ry = x.at(0.0), y.at(0.0)
    assert (rx.position, rx.velocity, rx.acceleration) == pytest.approx((0.04, 0.0, -0.04 * w**2))
    assert (ry.position, ry.velocity, ry.acceleration) == pytest.approx((0.0, 0.04 * w, 0.0))
    # t = 2.5 s is a quarter turn: x = 0 moving at -R w, y = R at rest
    rx, ry = x.at(2.5), y.at(2.5)
    assert rx.position == pytest.approx(0.0, abs=1e-15) and rx.velocity == pytest.approx(-0.04 * w)
    assert ry.position == pytest.approx(0.04) and ry.velocity == pytest.approx(0.0, abs=1e-15)
    assert math.hypot(rx.velocity, ry.velocity) == pytest.approx(0.025133, abs=1e-6)  # feed 25 mm/s
    assert rx.jerk == pytest.approx(0.04 * w**3)


def test_circle_continues_after_duration() -> None:
    c = Circle("y", revolutions=0.5)
    assert c.duration == 5.0
    assert c.at(12.5).position == pytest.approx(c.at(2.5).position)
    assert c.at(7.5).position == pytest.approx(-0.04)  # past its duration, not held at the end


@pytest.mark.parametrize("axis", ["x", "y"])
def test_circle_numeric_derivatives(axis: str) -> None:
    c = Circle(axis, radius=0.03, period=4.0, center=0.01, phase=0.3)
    dt = 1e-4
    t = np.arange(0.0, c.duration, dt)
    pos, vel, acc, jerk = c.sample(t)
    assert np.abs(pos - 0.01).max() == pytest.approx(0.03, rel=1e-6)
    sl = slice(1, -1)  # np.gradient is one-sided (first order) at the ends
    for f, df in ((pos, vel), (vel, acc), (acc, jerk)):
        scale = np.abs(df).max()
        assert np.abs(np.gradient(f, dt) - df)[sl].max() < 1e-6 * scale


@pytest.mark.parametrize("axis", ["x", "y"])
def test_circle_run_in_ramps_the_feed_from_rest_on_the_same_circle(axis: str) -> None:
    """run_in: the path speed rises from 0 to the feed by the cycloidal law (no velocity or acceleration
    step), on the circle of eq (25), which it then follows late by run_in / 2."""
    c, paper = Circle(axis, run_in=0.2), Circle(axis)
    assert c.duration == pytest.approx(10.1)
    dt = 1e-4
    t = np.arange(-0.01, c.duration, dt)
    pos, vel, acc, jerk = c.sample(t)
    r0 = c.at(0.0)
    assert (r0.position, r0.velocity, r0.acceleration) == (paper.start_position, 0.0, 0.0)
    sl = slice(1, -1)
    for f, df in ((pos, vel), (vel, acc), (acc, jerk)):
        assert np.abs(np.gradient(f, dt) - df)[sl].max() < 1e-3 * np.abs(df).max()
    other = Circle("y" if axis == "x" else "x", run_in=0.2).sample(t)
    xs, ys = (pos, other[0]) if axis == "x" else (other[0], pos)
    assert np.abs(np.hypot(xs, ys) - 0.04).max() < 1e-12  # the same circle throughout
    feed = 0.04 * math.pi / 5
    vx, vy = (vel, other[1]) if axis == "x" else (other[1], vel)
    speed = np.hypot(vx, vy)
    assert np.all(np.diff(speed[t <= 0.2]) >= -1e-15) and speed[t >= 0.2] == pytest.approx(feed)
    assert np.abs(acc).max() < 0.26  # 2 feed / run_in on y, not a step
    later = c.at(5.0 + 0.1)
    assert later.position == pytest.approx(paper.at(5.0).position, abs=1e-12)
    assert Circle(axis, run_in=0.0).sample(t)[1].tolist() == paper.sample(t)[1].tolist()  # eq (25) exactly


def test_library_circle_runs_in_and_the_reproduction_does_not() -> None:
    c = load_profile("circle", axis="y")
    assert c.run_in == 0.2 and c.at(0.0).velocity == 0.0
    assert Circle("y").at(0.0).velocity == pytest.approx(0.04 * math.pi / 5)  # bench/reproduce_004.py's


@pytest.mark.parametrize(
    ("kwargs", "field"), [({"axis": "z"}, "axis"), ({"radius": 0}, "radius"), ({"period": -1}, "period"),
                          ({"run_in": -0.1}, "run_in"),
                          ({"revolutions": 0}, "revolutions"), ({"phase": math.inf}, "phase")]
)
def test_circle_rejects_bad_arguments(kwargs: dict, field: str) -> None:
    with pytest.raises(ProfileError, match=f"^profile circle: {field}: "):
        Circle(**kwargs)


# ------------------------------------------------------------------------------------------- dwell
def test_dwell() -> None:
    d = Dwell(0.02, 1.5)
    assert d.duration == 1.5 and d.start_position == 0.02
    pos, vel, acc, jerk = d.sample(np.array([[-1.0, 0.0], [1.0, 9.0]]))
    assert pos.shape == (2, 2) and np.all(pos == 0.02) and not (vel.any() or acc.any() or jerk.any())
    with pytest.raises(ProfileError, match="^profile dwell: duration: must be >= 0"):
        Dwell(0.0, -1.0)


# ---------------------------------------------------------------------------------------- sequence
def test_sequence_plays_segments_on_their_own_clocks() -> None:
    a = PointToPoint(0.0, 0.01, 0.05, 0.5, 20.0)
    d = Dwell(0.01, 0.5)
    b = PointToPoint(0.01, -0.005, 0.05, 0.5, 20.0, hold_until=1.0)
    s = Sequence([a, d, b], name="three")
    assert s.duration == pytest.approx(a.duration + 0.5 + 1.0)
    assert list(s.offsets) == pytest.approx([0.0, a.duration, a.duration + 0.5])
    t = random_times(s, 300)
    got = s.sample(t)
    for i, ti in enumerate(t):
        k = 0 if ti < a.duration else 1 if ti < a.duration + 0.5 else 2
        seg, off = (a, d, b)[k], s.offsets[k]
        want = seg.at(ti - off)
        assert (want.position, want.velocity, want.acceleration, want.jerk) == tuple(g[i] for g in got)
        r = s.at(float(ti))
        assert (r.position, r.velocity, r.acceleration, r.jerk) == tuple(g[i] for g in got)
    assert s.start_position == 0.0 and s.end_position == -0.005
    assert s.at(-1.0).position == 0.0 and s.at(s.duration + 5).position == -0.005
    # 0-d input keeps its shape (the servo and helpers call sample(np.array(t)))
    assert s.sample(np.array(0.1))[0].shape == ()


def test_sequence_is_continuous_at_joins() -> None:
    s = back_and_forth()
    for off in s.offsets[1:]:
        before, after = s.sample(np.array([off - 1e-12, off]))[0]
        assert abs(after - before) < 1e-9


def test_sequence_rejects_gaps() -> None:
    a = PointToPoint(0.0, 0.01, 0.05, 0.5, 20.0, name="out")
    with pytest.raises(ProfileError) as exc:
        Sequence([a, Dwell(0.0100001, 0.5, name="pause")], name="gappy")
    assert str(exc.value) == (
        "profile gappy: segments[1] (pause) starts at 0.0100001 m but segments[0] (out) ends at 0.01 m"
    )
    Sequence([a, Dwell(0.01 + 5e-10, 0.5)])  # within 1e-9 m is continuous
    with pytest.raises(ProfileError, match="segments: need at least one"):
        Sequence([])
    with pytest.raises(ProfileError, match=r"segments\[0\]: not a profile"):
        Sequence([0.5])  # type: ignore[list-item]


def test_back_and_forth() -> None:
    speeds = [0.02, 0.05, 0.1]
    s = back_and_forth(0.01, 0.05, speeds, 0.5, 20.0, 0.3)
    assert 8.0 <= s.duration <= 12.0
    assert len(s.segments) == 12
    t = np.linspace(0.0, s.duration, 20_001)
    pos, vel, acc, _ = s.sample(t)
    assert pos[0] == 0.01 and pos[-1] == 0.01 and vel[-1] == 0.0
    assert pos.max() == pytest.approx(0.06) and pos.min() == pytest.approx(0.01)
    assert np.abs(vel).max() <= 0.1 + TOL and np.abs(acc).max() <= 0.5 + TOL
    for i, v in enumerate(speeds):  # each out-and-back pair cruises at its own speed
        out, back = s.segments[4 * i], s.segments[4 * i + 2]
        assert (out.vmax, back.vmax) == (v, v)
        assert out.target == pytest.approx(0.06) and back.target == pytest.approx(0.01)
    twice = back_and_forth(0.0, -0.02, [0.05], 0.5, 20.0, 0.1, repeats=2)
    assert len(twice.segments) == 8 and twice.sample(np.array([0.3]))[0][0] < 0  # negative first
    with pytest.raises(ProfileError, match="^profile back-and-forth: speeds\\[1\\]: must be > 0"):
        back_and_forth(speeds=[0.1, 0.0])
    with pytest.raises(ProfileError, match="^profile back-and-forth: repeats: "):
        back_and_forth(repeats=0)
    with pytest.raises(ProfileError, match="^profile back-and-forth: distance: must be non-zero"):
        back_and_forth(distance=0.0)


# ------------------------------------------------------------------------------------ check_limits
def test_check_limits_names_first_violation() -> None:
    with pytest.raises(ProfileError) as exc:
        check_limits(Circle("x"), position=(-0.03, 0.03))
    assert str(exc.value) == (
        "profile circle: position 0.040000 m at t=0.000 s is outside the soft limits [-0.03, 0.03] m"
    )
    with pytest.raises(ProfileError) as exc:
        check_limits(seed000(), vmax=0.05)
    msg = str(exc.value)
    assert msg.startswith("profile seed-000: velocity 0.05") and "exceeds the limit 0.05 m/s" in msg
    # v crosses 0.05 m/s during the acceleration phase, between 0.025 s and 0.1 s
    assert 0.025 < float(msg.split("t=")[1].split(" s")[0]) < 0.1
    with pytest.raises(ProfileError, match=r"^profile seed-000: acceleration 0\.5\d* m/s\^2 at t=0\.013 s"):
        check_limits(seed000(), amax=0.5)
    # The earliest violation wins: position leaves [0, 0.03] at ~0.4 s, velocity exceeds 0.01 at ~0.03 s.
    with pytest.raises(ProfileError, match="velocity"):
        check_limits(seed000(), position=(0.0, 0.03), vmax=0.01)


def test_check_limits_passes_compliant_profiles() -> None:
    check_limits(seed000(), position=(-0.01, 0.1), vmax=0.1, amax=1.0)
    check_limits(Circle("y"), position=(-0.04, 0.04), vmax=0.04 * math.pi / 5, amax=0.04 * (math.pi / 5) ** 2)
    check_limits(Circle("x"), position=(-0.05, 0.05), until=25.0)
    with pytest.raises(ProfileError, match="position limits: lower must be below upper"):
        check_limits(seed000(), position=(0.1, 0.0))
    with pytest.raises(ProfileError, match="rate: must be >= 1000"):
        check_limits(seed000(), rate=100.0)


def test_check_limits_catches_a_brief_excursion() -> None:
    # a 1 mm out-and-back lasting ~40 ms after a pause: the dense scan must catch its peak
    blip = Sequence([Dwell(0.0, 0.5), PointToPoint(0.0, 0.001, 1.0, 10.0, 1e5),
                     PointToPoint(0.001, 0.0, 1.0, 10.0, 1e5)])
    check_limits(blip, position=(-1.0, 0.002))
    with pytest.raises(ProfileError, match="outside the soft limits"):
        check_limits(blip, position=(-1.0, 0.0009))


# ----------------------------------------------------------------------------------------- library
def test_list_profiles() -> None:
    assert list_profiles() == LIBRARY


@pytest.mark.parametrize("name", LIBRARY)
@pytest.mark.parametrize("axis", ["x", "y"])
def test_every_library_file_loads(name: str, axis: str) -> None:
    p = load_profile(name, axis=axis)
    assert isinstance(p, Profile)
    assert p.name == name and p.duration > 0
    assert p.start_position == p.at(0.0).position
    t = random_times(p, 200)
    pos, vel, acc, jerk = p.sample(t)
    for i in range(0, 200, 7):
        r = p.at(float(t[i]))
        assert (r.position, r.velocity, r.acceleration, r.jerk) == (pos[i], vel[i], acc[i], jerk[i])
    check_limits(p, position=(-0.1, 0.1), vmax=0.2, amax=2.0)


def test_library_seed000_and_circle_match_the_papers() -> None:
    p = load_profile("seed-000", axis="z")  # non-circle kinds ignore the axis
    assert isinstance(p, PointToPoint)
    assert (p.start, p.target, p.vmax, p.amax, p.jmax) == (0.0, 0.065, 0.1, 1.0, 40.0)
    assert p.move_time == pytest.approx(0.775) and p.duration == 2.5
    x, y = load_profile("circle", axis="x"), load_profile("circle", axis="y")
    assert x.start_position == pytest.approx(0.04) and y.start_position == pytest.approx(0.0)
    # eq (25)'s quarter turn at 2.5 s, 0.1 s later: the library's circle runs in over 0.2 s
    assert x.at(2.6).position == pytest.approx(0.0, abs=1e-15) and y.at(2.6).position == pytest.approx(0.04)
    assert x.duration == pytest.approx(10.1)
    with pytest.raises(ProfileError, match=r"^profiles/library/circle\.toml: axis: .*got 'z'"):
        load_profile("circle", axis="z")


def test_library_back_and_forth_returns_to_start() -> None:
    p = load_profile("back-and-forth")
    assert 8.0 <= p.duration <= 12.0
    end = p.at(p.duration)
    assert end.position == p.start_position == 0.0 and end.velocity == 0.0
    pos, vel, _, _ = p.sample(np.linspace(0, p.duration, 10_001))
    assert pos.max() == pytest.approx(0.05)
    # three speeds, six reversals of direction
    signs = np.sign(vel[np.abs(vel) > 1e-6])
    assert np.count_nonzero(np.diff(signs)) == 5
    assert np.abs(vel).max() == pytest.approx(0.1)


def test_short_move_is_quick() -> None:
    p = load_profile("short-move")
    assert p.at(p.duration).position == 0.01 and p.duration <= 1.0


def test_load_by_path_and_pathlike(tmp_path: Path) -> None:
    f = tmp_path / "mine.toml"
    f.write_text('kind = "dwell"\nposition = 0.003\nduration = 0.2\n')
    for arg in (f, str(f)):
        p = load_profile(arg)
        assert isinstance(p, Dwell) and p.name == "mine" and p.position == 0.003
    with pytest.raises(ProfileError, match="no such library profile .*available: back-and-forth, circle"):
        load_profile("no-such-profile")


def test_sequence_toml_with_implicit_starts(tmp_path: Path) -> None:
    f = tmp_path / "seq.toml"
    f.write_text(
        """
        kind = "sequence"
        description = "out, pause, a back-and-forth, back, circle quarter"
        [[segments]]
        kind = "ptp"
        start = 0.0
        target = 0.04
        vmax = 0.05
        amax = 0.5
        jmax = 20.0
        [[segments]]
        kind = "dwell"
        duration = 0.25
        [[segments]]
        kind = "back-and-forth"
        distance = -0.01
        speeds = [0.02]
        amax = 0.5
        jmax = 20.0
        dwell = 0.1
        [[segments]]
        kind = "circle"
        radius = 0.04
        period = 10.0
        revolutions = 0.25
        """
    )
    p = load_profile(f, axis="x")
    assert isinstance(p, Sequence) and len(p.segments) == 4
    assert [s.name for s in p.segments][:2] == ["seq.segments[0]", "seq.segments[1]"]
    assert p.segments[1].position == pytest.approx(0.04)
    assert p.at(p.duration).position == pytest.approx(0.0, abs=1e-12)  # the x circle, a quarter turn on
    with pytest.raises(ProfileError, match=r"seq\.toml: segments\[3\]: the circle starts at 0 m on axis y"):
        load_profile(f, axis="y")  # the y circle starts at 0, not where the x-ready sequence is


PTP = 'kind = "ptp"\nstart = 0.0\ntarget = 0.065\nvmax = 0.1\namax = 1.0\njmax = 40.0\n'
BNF = 'kind = "back-and-forth"\nstart = 0.0\ndistance = 0.05\nspeeds = [0.02]\namax = 0.5\njmax = 20.0\n'
SEQ = '''kind = "sequence"
[[segments]]
kind = "dwell"
position = 0.0
duration = 0.1
[[segments]]
'''


@pytest.mark.parametrize(
    ("text", "key", "detail"),
    [
        (PTP.replace("vmax = 0.1", "vmax = "), "vmax", "invalid TOML"),  # syntax: the quoted line names it
        (PTP.replace("vmax = 0.1\n", ""), "vmax", "missing (required for kind 'ptp')"),
        (PTP.replace("vmax = 0.1", 'vmax = "fast"'), "vmax", "expected a number > 0, got 'fast'"),
        (PTP.replace("vmax = 0.1", "vmx = 0.1"), "vmx", "unknown key for kind 'ptp'"),
        (PTP.replace("amax = 1.0", "amax = -1.0"), "amax", "expected a number > 0, got -1.0"),
        (PTP.replace("jmax = 40.0", "jmax = nan"), "jmax", "expected a number > 0, got nan"),
        (PTP.replace("jmax = 40.0", "jmax = true"), "jmax", "expected a number > 0, got True"),
        (PTP + "hold_until = -2\n", "hold_until", "expected a number >= 0, got -2"),
        (PTP.replace('"ptp"', '"spline"'), "kind", "expected one of ptp, circle"),
        (PTP.replace('kind = "ptp"\n', ""), "kind", "missing"),
        (PTP + "description = 3\n", "description", "expected a string"),
        ('kind = "circle"\nradius = 0.04\n', "period", "missing"),
        ('kind = "circle"\nradius = 0.04\nperiod = 10\ncenter = [0.0]\n', "center", "two numbers"),
        ('kind = "circle"\nradius = 0.04\nperiod = 10\ncenter = [0, "a"]\n', "center[1]", "a number"),
        ('kind = "dwell"\nposition = 0.0\nduration = -1\n', "duration", "expected a number >= 0, got -1"),
        (BNF + "dwell = 0.3\nrepeats = 1.5\n", "repeats", "expected an integer >= 1, got 1.5"),
        (BNF.replace("[0.02]", "[0.02, -0.05]") + "dwell = 0.3\n", "speeds[1]", "expected a number > 0"),
        (BNF.replace("[0.02]", "[]") + "dwell = 0.3\n", "speeds", "non-empty array"),
        (BNF.replace("distance = 0.05", "distance = 0") + "dwell = 0.3\n", "distance", "non-zero"),
        (SEQ + 'kind = "dwell"\nposition = 0.5\nduration = 1\n', "segments[1].position", "previous segment"),
        (SEQ + 'kind = "ptp"\ntarget = 0.01\nvmax = 0.1\namax = 1\njmax = "x"\n', "segments[1].jmax", "'x'"),
        (SEQ + 'kind = "dwell"\nduration = 1.0\nextra = 1\n', "segments[1].extra", "unknown key"),
        ('kind = "sequence"\nsegments = []\n', "segments", "one or more [[segments]] tables"),
    ],
)
def test_bad_toml_names_file_and_key(tmp_path: Path, text: str, key: str, detail: str) -> None:
    f = tmp_path / "bad-profile.toml"
    f.write_text(text)
    with pytest.raises(ProfileError) as exc:
        load_profile(f)
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg.startswith(f"{f}: ")
    assert key in msg and detail in msg


def test_bad_toml_message_shape(tmp_path: Path) -> None:
    f = tmp_path / "x.toml"
    f.write_text(PTP.replace("vmax = 0.1", 'vmax = "fast"'))
    with pytest.raises(ProfileError) as exc:
        load_profile(f)
    assert str(exc.value) == f"{f}: vmax: expected a number > 0, got 'fast'"


def test_unreadable_files(tmp_path: Path) -> None:
    missing = tmp_path / "nope.toml"
    with pytest.raises(ProfileError, match=r"nope\.toml: cannot read: No such file"):
        load_profile(missing)
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"kind = \"\xff\xfe\"\n")
    with pytest.raises(ProfileError, match=r"bin\.toml: cannot read: not UTF-8"):
        load_profile(binary)
    with pytest.raises(ProfileError, match=r"tmp.*: cannot read"):
        load_profile(str(tmp_path) + "/")  # a directory
