"""`echoloc head check`: a sensor head's file read, checked and drawn."""

from __future__ import annotations

from pathlib import Path

import click
from rich.table import Table
from rich.text import Text

from echoloc.cli.app import _check_plot, _path_option, cli, stderr, stdout
from echoloc.errors import EchoLocError
from echoloc.io.head import check_head, load_head


@cli.group(name="head")
def head_group() -> None:
    """Sensor heads: the TOML file that describes one (docs/HEAD.md)."""


@head_group.command(name="check")
@click.argument("head_path", metavar="HEAD.toml", type=click.Path(path_type=Path))
@_path_option("--plot", "plot_path", help="Draw the head and its beams to this PNG.")
def head_check_command(head_path: Path, plot_path: Path | None) -> None:
    """Read HEAD.toml, show its transducers, wiring and figures, and say what is wrong with it.

    Exits with 2 when the head cannot work as described (frames that overlap, a carrier
    above Nyquist, receivers at one place); notes are warnings.
    """
    _check_plot(plot_path)
    head = load_head(head_path)
    check = check_head(head)
    header = head.header
    title = f"{head.name}: {head.description}" if head.description else head.name
    table = Table(title=Text(title))  # the user's own words, never read as markup
    for column in ("transducer", "x mm", "y mm", "z mm", "axis", "channel"):
        table.add_column(column, justify="right")
    axes = (header.transmitter_axes, header.receiver_axes)
    for kind, positions, axis_rows in (
        ("tx", header.transmitters_m, axes[0]),
        ("rx", header.receivers_m, axes[1]),
    ):
        for i, position in enumerate(positions):
            axis = (
                "(0, 0, 1)" if axis_rows is None else "(" + ", ".join(f"{v:.2f}" for v in axis_rows[i]) + ")"
            )
            if kind == "rx":
                channel = str(head.channel_order[i])
            else:
                channel = "-" if head.output_channel is None else f"out {head.output_channel}"
            table.add_row(f"{kind} {i}", *(f"{v * 1e3:.1f}" for v in position), axis, channel)
    stdout.print(table)
    beam = "unknown" if check.beam_half_angle_deg is None else f"±{check.beam_half_angle_deg:.1f}° (-3 dB)"
    loopback = "none" if head.loopback_channel is None else f"channel {head.loopback_channel}"
    lines = [
        f"signal {header.signal_kind}, {header.sample_rate_hz:g} Hz, {header.n_samples} samples a frame "
        f"({check.frame_s * 1e3:.2f} ms), {head.frame_rate_hz:g} frames/s",
        f"pulse {check.pulse_s * 1e3:.3f} ms at {header.carrier_hz or 0:g} Hz; "
        f"blind to {check.blind_range_m:.3f} m, hears to {check.max_range_m:.2f} m "
        f"(c = {header.speed_of_sound_m_s:.1f} m/s)",
        f"beam {beam}; loopback {loopback}",
        f"capture: {head.n_channels} channels of {head.adc.format} ({head.adc.bits} bits, offset "
        f"{head.adc.offset:g}, full scale {head.adc.full_scale:g} counts): "
        f"{head.frame_bytes()} bytes a frame, {check.bytes_per_s / 1e6:.2f} MB/s",
    ]
    for line in lines:
        click.echo(line)  # plain lines, never wrapped
    for note in check.notes:
        stderr.print(f"echoloc: warning: {head_path}: {note}", markup=False, highlight=False)
    if plot_path is not None:
        from echoloc.plots.head import plot_head

        stderr.print(
            f"echoloc: head: drew {plot_head(head, check, plot_path)}", markup=False, highlight=False
        )
    if check.problems:
        raise EchoLocError(f"{head_path}: " + "; ".join(check.problems))
