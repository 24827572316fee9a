"""``afmctl emulate``: the device side, served over the wires."""

from __future__ import annotations

import sys
import time

import click

from afmctl.cli.base import fail, load_profile_or_exit, main


@main.command()
@click.option("--profile", "profile_path", type=click.Path(dir_okay=False),
              help="Stage profile with an [emulator] section (default: the shipped emulated one).")
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
    if serial_where.startswith("socket://") and not (host or bind_any):
        serial_where = serial_where.replace("socket://:", f"socket://{bind}:")
    from drivers.device.emulated import serve_all
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
        fail(f"cannot serve: {exc}", 1)

