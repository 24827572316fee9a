"""``afmctl emulate``, ``conformance``, ``status``, ``safe``: the stage itself, apart from a run."""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import click

from afmctl.cli.base import Finite, fail, load_profile_or_exit, main


@main.command()
@click.option("--profile", "profile_path",
              help="Stage profile with an [emulator] section, a file or a shipped name (default: "
                   "the shipped emulated one).")
@click.option("--modbus-port", type=click.IntRange(0, 65535), default=5020, show_default=True,
              help="Modbus TCP port (0: any free port).")
@click.option("--serial", "serial_where", default="pty", show_default=True,
              help="Serial protocol on 'pty' or 'socket://HOST:PORT'.")
@click.option("--no-rtu", is_flag=True, help="Do not serve Modbus RTU on a pty.")
@click.option("--host", default=None, help="Address to bind (default 127.0.0.1).")
@click.option("--bind-any", is_flag=True, help="Bind 0.0.0.0 (reachable from other machines).")
@click.option("--read-only", is_flag=True, help="Refuse every command that changes the output.")
def emulate(profile_path: str | None, modbus_port: int, serial_where: str, no_rtu: bool,
            host: str | None, bind_any: bool, read_only: bool) -> None:
    """Serve an emulated stage (Modbus TCP, Modbus RTU on a pty, serial protocol) until Ctrl-C."""
    prof = load_profile_or_exit(profile_path)
    if prof.emulator is None:
        fail(f"bad profile: {prof.name}: missing table [emulator]")
    if bind_any and host is not None:
        raise click.UsageError("give --host or --bind-any, not both")
    bind = "0.0.0.0" if bind_any else (host or "127.0.0.1")
    _check_serial_where(serial_where)
    if serial_where.startswith("socket://") and not (host or bind_any):
        serial_where = serial_where.replace("socket://:", f"socket://{bind}:")
    from afmctl.drivers.device.emulated import serve_all
    try:
        with serve_all(prof, host=bind, modbus_port=modbus_port, serial=serial_where,
                       rtu=not no_rtu, read_only=read_only or None) as where:
            for name, addr in where.items():
                click.echo(f"{name}: {addr}")
            click.echo("serving; Ctrl-C to stop", err=True)
            sys.stdout.flush()
            while True:
                time.sleep(3600)
    except KeyboardInterrupt:
        click.echo("stopped", err=True)
    except (OSError, ValueError) as exc:
        taken = f":{modbus_port}" in str(exc) and modbus_port != 0
        fail(f"cannot serve: {exc}" + (f"; another program holds port {modbus_port}: give "
                                       f"--modbus-port another port, or 0 for any free one"
                                       if taken else ""), 1)


def _check_serial_where(where: str) -> None:
    """``--serial``: ``pty`` or ``socket://[HOST]:PORT`` (exit 2 naming it otherwise)."""
    import re
    if where == "pty":
        return
    m = re.fullmatch(r"socket://([^:/]*):(\d{1,5})", where)
    if m is None or int(m.group(2)) > 65535:
        raise click.BadParameter(f"{where!r}: 'pty' or 'socket://HOST:PORT' (PORT 0-65535, 0 for "
                                 f"any free port; HOST may be left out)", param_hint="'--serial'")



PROFILE_HELP = ("Stage profile: a TOML file, or a shipped one by name (emulated, lab-serial, "
                "lab-modbus); default: the shipped emulated one.")


@main.command()
@click.option("--profile", "profile_path", help=PROFILE_HELP)
@click.option("--max-voltage", type=float, default=None,
              help="Largest |voltage| the check commands, V (default: 10 % of the profile's "
                   "voltage span).")
@click.option("--yes", is_flag=True, help="Confirm that the stage may move (required on hardware).")
@click.option("--json", "as_json", is_flag=True, help="Results as one JSON object on stdout.")
def conformance(profile_path: str | None, max_voltage: float | None, yes: bool,
                as_json: bool) -> None:
    """Check a stage against docs/reference/protocol.md, clause by clause (exit 0 only if all pass, 1 if
    one fails, 3 if the host fell behind and could not judge a timing requirement).

    On a hardware profile it talks to the stage the profile names (serial or Modbus) and moves it
    within +-max-voltage: pass --yes. On the emulated profile it serves the emulated device on
    every wire (serial on a pty and on socket://, Modbus TCP, Modbus RTU) and checks each."""
    prof = load_profile_or_exit(profile_path)
    from afmctl.drivers import conformance as cf
    from afmctl.files.profile import EmulatedTransport
    try:
        lo, hi = cf.bounds(prof, max_voltage)
    except ValueError as exc:
        fail(str(exc))
    emulated = isinstance(prof.transport, EmulatedTransport)
    if not emulated and not yes:
        fail(f"conformance moves the stage of profile {prof.name!r} between {lo:g} and {hi:g} V "
             f"and plays runs on it; pass --yes to confirm (--max-voltage bounds it)")
    report: dict[str, list[dict[str, object]]] = {}
    for wire, opened in cf.wires(prof, emulated):
        click.echo(f"conformance: {wire}, commanding {lo:g} .. {hi:g} V", err=True)
        with opened as stage:
            results = cf.run(stage, prof, max_voltage,
                             lambda what: click.echo(f"  checking {what}", err=True))
        report[wire] = [dict(clause=r.clause, title=r.title, passed=r.passed, detail=r.detail,
                             label=r.label, host_fell_behind=r.host_late) for r in results]
        if not as_json:
            _print_table(wire, results)
    rows = [r for rows in report.values() for r in rows]
    ok = all(r["passed"] is not False for r in rows)
    late = any(r["host_fell_behind"] for r in rows)
    if as_json:
        click.echo(json.dumps({"profile": prof.name, "max_voltage_V": max(abs(lo), abs(hi)),
                               "passed": ok and not late, "wires": report}))
    if not ok or late:
        sys.exit(1 if not ok else 3)


def _print_table(wire: str, results: list) -> None:  # noqa: ANN001 (list[conformance.Result])
    click.echo(f"{wire}:")
    word = {True: "PASS", False: "FAIL", None: "n/a "}
    for r in results:
        click.echo(f"  {'LATE' if r.host_late else word[r.passed]}  {r.clause:17s} "
                   f"{r.title:38s} {r.detail}")
    counts = [sum(r.passed is v and not r.host_late for r in results) for v in (True, False, None)]
    late = sum(r.host_late for r in results)
    click.echo("  {} passed, {} failed, {} not applicable".format(*counts)
               + (f", {late} not judged: the host fell behind" if late else ""))


@main.command()
@click.option("--profile", "profile_path", help=PROFILE_HELP)
@click.option("--read/--no-read", default=True, show_default=True,
              help="Read the sensor: a 10 ms run holding the present output (nothing moves).")
@click.option("--json", "as_json", is_flag=True, help="One JSON object on stdout.")
def status(profile_path: str | None, read: bool, as_json: bool) -> None:
    """Show the stage's state: identity, limits, output, run, watchdog, last error and the
    sensor's reading at the present output (on a stage of several axes, per axis too)."""
    prof = load_profile_or_exit(profile_path)
    from afmctl.drivers import open_stage
    from afmctl.drivers.protocol import ERRORS
    from afmctl.errors import LimitMismatchError
    mismatch = None
    with open_stage(prof) as stage:
        st, idn, (v_min, v_max, slew) = stage.status(), stage.identify(), stage.limits()
        try:
            stage.check_limits()
        except LimitMismatchError as exc:
            mismatch = str(exc)
        why = ""
        if not read:
            why = "not read (--no-read)"
        elif mismatch or st.running or st.read_only:
            why = ("not read: " + ("the profile's limits do not match the device's" if mismatch
                                   else "a run is playing" if st.running
                                   else "a read-only device plays no run"))
        readings = _readings(stage, prof, read=not why)
        axes = _axes(stage, prof, readings) if len(prof.axis_names) > 1 else None
    reading = readings[0]
    fields = {"profile": prof.name, "identity": idn, "channels": stage.channels,
              "running": st.running,
              "output_V": st.output_v, "sample_rate_Hz": st.sample_rate_hz,
              "v_min_V": v_min, "v_max_V": v_max, "slew_V_per_ms": slew,
              "play_position_samples": st.play_position, "run_samples": st.run_samples,
              "runs": st.run_count, "table_length_samples": st.table_length,
              "recorder_fill_samples": st.recorder_fill, "watchdog_s": st.watchdog_s,
              "watchdog_armed": st.watchdog_armed, "watchdog_expired": st.watchdog_expired,
              "read_only": st.read_only, "last_error": st.last_error,
              "last_error_text": ERRORS.get(st.last_error, "unknown code"),
              "reading_um": None if reading is None else reading.mean_um,
              "reading_sd_um": None if reading is None else reading.sd_um}
    if axes is not None:
        fields["axes"] = axes
    if mismatch:
        click.echo(f"warning: {mismatch}", err=True)
    if as_json:
        click.echo(_json(fields))
        return
    for key, value in fields.items():
        if key in ("last_error_text", "reading_sd_um", "axes"):
            continue
        if key == "last_error":
            value = f"{value} ({fields['last_error_text']})"
        elif key == "reading_um":
            value = why if reading is None else (
                f"{reading.mean_um:.4f} (mean of {reading.samples} samples at "
                f"{reading.output_v:g} V, sd {reading.sd_um:.4f} um)")
        click.echo(f"{key}: {value}")
    for name, ax in (axes or {}).items():
        click.echo(f"axis {name}: " + ", ".join(
            f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in ax.items()))


def _readings(stage: Any, prof: Any, read: bool) -> list[Any]:
    """Each axis's sensor reading at its present output (None each if not ``read``)."""
    if not read:
        return [None] * len(prof.axis_names)
    from afmctl.experiment import runner
    return [runner.move_and_read(stage, stage.voltage(c), prof.axis(name).limits,
                                 prof.sample_rate_hz, 0.01, channel=c)
            for c, name in enumerate(prof.axis_names)]


def _axes(stage: Any, prof: Any, readings: list[Any]) -> dict[str, dict[str, object]]:
    """``status``'s ``axes``: each axis's channel, output, limits and reading."""
    out = {}
    for c, (name, r) in enumerate(zip(prof.axis_names, readings, strict=True)):
        v_min, v_max, slew = stage.limits(c)
        out[name] = {"channel": c, "output_V": stage.voltage(c), "v_min_V": v_min,
                     "v_max_V": v_max, "slew_V_per_ms": slew,
                     "reading_um": None if r is None else r.mean_um,
                     "reading_sd_um": None if r is None else r.sd_um}
    return out


def _json(fields: dict[str, object]) -> str:
    """One JSON object, a reading that is not a number as null."""
    from afmctl.experiment.runner import json_ready
    return json.dumps(json_ready(fields))


@main.command("set")
@click.option("--profile", "profile_path", help=PROFILE_HELP)
@click.option("--voltage", type=Finite(), required=True,
              help="Output to bring the stage to and leave it at, V (within the profile's "
                   "limits).")
@click.option("--hold", "hold_s", type=Finite(0.001), default=0.1, show_default=True,
              help="Time held at the voltage while the sensor is read, s.")
@click.option("--axis", "axis_name", default=None,
              help="The axis to move on a stage of several (x, y; default x), the others held.")
@click.option("--channel", type=click.IntRange(0), default=None,
              help="The channel to move (0 is x, 1 is y): the same as --axis.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object on stdout.")
def set_voltage(profile_path: str | None, voltage: float, hold_s: float, axis_name: str | None,
                channel: int | None, as_json: bool) -> None:
    """Bring the stage to a DC voltage by hand and read its sensor there.

    The output ramps from where it is to VOLTAGE (a raised cosine at a quarter of the profile's
    usable slew rate, checked like any waveform), holds it for --hold and prints the mean reading
    over the hold; it then stays there (`afmctl safe` ramps it back to 0 V). For bringing a stage
    up: find where the sensor reads at the ends of the range before anything else moves it."""
    from afmctl.cli.base import opened_stage
    from afmctl.experiment import runner
    prof = load_profile_or_exit(profile_path)
    channel = _channel(prof, axis_name, channel)
    name = prof.axis_names[channel]
    lim = prof.axis(name).limits
    if not lim.v_min <= voltage <= lim.v_max:
        axis = f" axis {name}" if len(prof.axis_names) > 1 else ""
        fail(f"--voltage {voltage:g} V is outside profile {prof.name!r}'s{axis} limits "
             f"[{lim.v_min:g}, {lim.v_max:g}] V")
    if hold_s > 60:
        fail(f"--hold {hold_s:g} s: at most 60 s")
    with opened_stage(prof) as stage:
        r = runner.move_and_read(stage, voltage, lim, prof.sample_rate_hz, hold_s, channel)
        out_v = stage.voltage(channel)
    if as_json:
        click.echo(_json({"output_V": out_v, "reading_um": r.mean_um, "reading_sd_um": r.sd_um,
                          "samples": r.samples}))
        return
    click.echo(f"output {out_v:g} V; reading {r.mean_um:.4f} um (mean of {r.samples} samples "
               f"over {hold_s:g} s, sd {r.sd_um:.4f} um)")


def _channel(prof: Any, axis_name: str | None, channel: int | None) -> int:
    """The channel ``--axis`` or ``--channel`` names (0 if neither); exit 2 naming a wrong one."""
    names = prof.axis_names
    if axis_name is not None and channel is not None:
        raise click.UsageError("give --axis or --channel, not both")
    if axis_name is not None:
        if axis_name not in names:
            fail(f"--axis {axis_name}: profile {prof.name!r} has axes {', '.join(names)}")
        return int(names.index(axis_name))
    if channel is not None and channel >= len(names):
        fail(f"--channel {channel}: profile {prof.name!r} has {len(names)} axis/axes "
             f"(channels 0 .. {len(names) - 1})")
    return channel or 0


@main.command()
@click.option("--profile", "profile_path", help=PROFILE_HELP)
def safe(profile_path: str | None) -> None:
    """Stop the stage and ramp every output to 0 V (the safe state)."""
    prof = load_profile_or_exit(profile_path)
    from afmctl.drivers import open_stage
    with open_stage(prof) as stage:
        stage.safe_state()
        out = stage.voltages()
    if out.size == 1:
        click.echo(f"safe: stopped, output {out[0]:g} V")
        return
    names = list(prof.axis_names) + [f"channel {c}" for c in range(len(prof.axis_names), out.size)]
    click.echo("safe: stopped, outputs " + ", ".join(f"{n} {v:g} V" for n, v in zip(names, out,
                                                                                   strict=False)))
