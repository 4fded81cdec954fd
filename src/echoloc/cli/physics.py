"""`echoloc waveform`, `air`, `beam` and `design`: the physics and the receiver spacing."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import click
import numpy as np
from rich.table import Table

from echoloc.cli.app import _check_plot, _finite, _json_safe, _path_option, cli, stderr, stdout
from echoloc.cli.processing import _MAX_SAMPLE_RATE_HZ
from echoloc.errors import EchoLocError
from echoloc.physics.air import (
    absorption_db_per_m,
    air_density_kg_m3,
    characteristic_impedance_rayl,
    speed_of_sound_cramer_m_s,
    speed_of_sound_m_s,
)
from echoloc.physics.transducer import (
    PRESETS,
    ShadingKind,
    grating_lobe_angles,
    impulse_response,
    near_field_length_m,
    piston_beam_angles,
    shading_weights,
    transducers_to_cover,
)
from echoloc.physics.waveform import (
    Carrier,
    CodeMetrics,
    WaveformMetrics,
    code_by_name,
    code_metrics,
    waveform_by_name,
    waveform_metrics,
)
from echoloc.sim.scenefile import load_scene

# --- physics: waveform, air, beam ---------------------------------------------------


def _metrics_record(metrics: WaveformMetrics) -> dict[str, float]:
    return {k: float(v) for k, v in asdict(metrics).items()}


@cli.command(name="waveform")
@click.argument("name")
@click.option(
    "--carrier", "carrier_hz", type=float, default=50e3, show_default=True, help="Carrier frequency, Hz."
)
@click.option("--cycles-per-bit", type=int, default=4, show_default=True, help="Carrier cycles per code bit.")
@click.option("--sample-rate", "sample_rate_hz", type=float, default=200e3, show_default=True, help="Hz.")
@click.option("--carrier-shape", type=click.Choice(["sine", "square"]), default="sine", show_default=True)
@click.option(
    "--transducer",
    "transducer_name",
    type=click.Choice([*PRESETS, "none"]),
    default="electrostatic50",
    show_default=True,
    help="Transmit-receive pair whose band-pass response the echo goes through.",
)
@click.option(
    "--speed-of-sound", "speed_of_sound_m_s", type=float, default=343.2, show_default=True, help="m/s."
)
@click.option("--json", "as_json", is_flag=True, help="One JSON object with the figures.")
@_path_option("--plot", default=None, help="Draw pulse, spectrum and correlation.")
def waveform_command(
    name: str,
    carrier_hz: float,
    cycles_per_bit: int,
    sample_rate_hz: float,
    carrier_shape: Carrier,
    transducer_name: str,
    speed_of_sound_m_s: float,
    as_json: bool,
    plot: Path | None,
) -> None:
    """Figures of merit of a pulse NAME, before and after a transducer pair.

    NAME is a code on a carrier (barker13, barker4b, golay16a, mls7, kasami6:2), a
    burst (tone16, polaroid) or a chirp (lfm, hfm). Reports the peak-to-sidelobe
    ratio, integrated sidelobe level, -3 dB main lobe and range resolution of the
    matched filter: for the emitted pulse, and after the transducer pair with the
    emitted pulse as template (the report's SENT) and with the received pulse
    (matched).
    """
    for option, value in (("--carrier", carrier_hz), ("--sample-rate", sample_rate_hz)):
        _finite(option, value, positive=True)
    _finite("--sample-rate", sample_rate_hz, maximum=_MAX_SAMPLE_RATE_HZ)
    if not carrier_hz < sample_rate_hz / 2:
        nyquist_hz = sample_rate_hz / 2
        raise EchoLocError(
            f"--carrier {carrier_hz:g} Hz must be below half --sample-rate ({nyquist_hz:g} Hz)"
        )
    _finite("--speed-of-sound", speed_of_sound_m_s, positive=True)
    _check_plot(plot)
    pulse = waveform_by_name(
        name,
        carrier_hz=carrier_hz,
        cycles_per_bit=cycles_per_bit,
        sample_rate_hz=sample_rate_hz,
        carrier=carrier_shape,
    )
    rows: list[tuple[str, WaveformMetrics]] = [
        ("emitted (autocorrelation)", waveform_metrics(pulse, speed_of_sound_m_s=speed_of_sound_m_s))
    ]
    transducer = None if transducer_name == "none" else PRESETS[transducer_name]
    if transducer is not None:
        response = impulse_response(transducer, sample_rate_hz)
        for label, template in (("SENT template", "sent"), ("matched", "received")):
            rows.append(
                (
                    f"after {transducer.name} pair, {label}",
                    waveform_metrics(
                        pulse, response=response, template=template, speed_of_sound_m_s=speed_of_sound_m_s
                    ),
                )
            )
    try:
        code: CodeMetrics | None = code_metrics(code_by_name(name))
    except EchoLocError:
        code = None
    if as_json:
        record: dict[str, Any] = {
            "waveform": pulse.name,
            "sample_rate_hz": pulse.sample_rate_hz,
            "carrier_hz": pulse.carrier_hz,
            "samples": len(pulse.samples),
            "duration_s": pulse.duration_s,
            "transducer": transducer_name,
            "code": None if code is None else {k: float(v) for k, v in asdict(code).items()},
            "metrics": {label: _metrics_record(m) for label, m in rows},
        }
        click.echo(json.dumps(_json_safe(record), allow_nan=False))
    else:
        stdout.print(
            f"[bold]{pulse.name}[/bold]: {len(pulse.samples)} samples at {sample_rate_hz / 1e3:g} kHz, "
            f"{pulse.duration_s * 1e3:.4g} ms, carrier {pulse.carrier_hz / 1e3:g} kHz"
            + (
                ""
                if code is None
                else f"; code: PSL {code.psl:g} of {code.length}, merit factor {code.merit_factor:.2f}"
            )
        )
        table = Table()
        for column in (
            "matched-filter output",
            "PSLR",
            "PSLR dB",
            "ISLR dB",
            "-3 dB lobe µs",
            "resolution mm",
            "peak lag µs",
        ):
            table.add_column(column, justify="right")
        for label, m in rows:
            table.add_row(
                label,
                f"{m.pslr_ratio:.2f}",
                f"{m.pslr_db:.1f}",
                f"{m.islr_db:.1f}",
                f"{m.mainlobe_width_s * 1e6:.1f}",
                f"{m.range_resolution_m * 1e3:.2f}",
                f"{m.peak_lag_s * 1e6:.1f}",
            )
        stdout.print(table)
    if plot is not None:
        from echoloc.plots.physics import plot_waveform

        written = plot_waveform(pulse, plot, transducer=transducer)
        stderr.print(f"plot written to {written}")


@cli.command(name="air")
@click.option("--temperature", "temperature_c", type=float, default=20.0, show_default=True, help="°C.")
@click.option(
    "--humidity", "relative_humidity", type=float, default=0.5, show_default=True, help="Fraction 0..1."
)
@click.option("--pressure", "pressure_pa", type=float, default=101325.0, show_default=True, help="Pa.")
@click.option(
    "--frequency",
    "frequencies_hz",
    type=float,
    multiple=True,
    default=(40e3, 50e3),
    show_default=True,
    help="Frequencies for absorption, Hz (repeat the option for several).",
)
@click.option("--json", "as_json", is_flag=True, help="One JSON object with the figures.")
@_path_option("--plot", default=None, help="Draw absorption and speed of sound.")
def air_command(
    temperature_c: float,
    relative_humidity: float,
    pressure_pa: float,
    frequencies_hz: tuple[float, ...],
    as_json: bool,
    plot: Path | None,
) -> None:
    """Speed of sound, impedance and absorption (ISO 9613-1) for the given air."""
    _check_plot(plot)
    _finite("--temperature", temperature_c, minimum=-90.0)
    if temperature_c > 100:
        raise EchoLocError(f"--temperature must be at most 100 °C, got {temperature_c}")
    _finite("--humidity", relative_humidity, minimum=0.0)
    if relative_humidity > 1:
        raise EchoLocError(f"--humidity is a fraction 0..1, got {relative_humidity}")
    _finite("--pressure", pressure_pa, positive=True)
    for f in frequencies_hz:
        _finite("--frequency", f, positive=True)
    c = float(speed_of_sound_m_s(temperature_c, relative_humidity, pressure_pa))
    try:
        c_cramer: float | None = float(
            speed_of_sound_cramer_m_s(temperature_c, relative_humidity, pressure_pa)
        )
    except EchoLocError:
        c_cramer = None  # outside Cramer's range of validity
    density = float(air_density_kg_m3(temperature_c, relative_humidity, pressure_pa))
    impedance = float(characteristic_impedance_rayl(density, c))
    freqs = np.array(frequencies_hz, dtype=float)
    alpha = absorption_db_per_m(freqs, temperature_c, relative_humidity, pressure_pa)
    if as_json:
        click.echo(
            json.dumps(
                {
                    "temperature_c": temperature_c,
                    "relative_humidity": relative_humidity,
                    "pressure_pa": pressure_pa,
                    "speed_of_sound_m_s": c,
                    "speed_of_sound_cramer_m_s": c_cramer,
                    "density_kg_m3": density,
                    "impedance_rayl": impedance,
                    "absorption": [
                        {"frequency_hz": float(f), "wavelength_m": c / float(f), "db_per_m": float(a)}
                        for f, a in zip(freqs, alpha, strict=True)
                    ],
                }
            )
        )
    else:
        stdout.print(
            f"Air at {temperature_c:g} °C, {relative_humidity:.0%} RH, {pressure_pa / 1e3:g} kPa: "
            f"c = {c:.2f} m/s (ideal mixture)"
            + (f", {c_cramer:.2f} m/s (Cramer 1993)" if c_cramer is not None else ", outside Cramer's range")
            + f"; ρ = {density:.4f} kg/m³; Z = ρc = {impedance:.1f} rayl"
        )
        table = Table()
        for column in (
            "frequency kHz",
            "wavelength mm",
            "absorption dB/m",
            "loss at 1 m range dB",
            "at 2 m range dB",
        ):
            table.add_column(column, justify="right")
        for f, a in zip(freqs, alpha, strict=True):
            table.add_row(f"{f / 1e3:g}", f"{c / f * 1e3:.3f}", f"{a:.3f}", f"{2 * a:.2f}", f"{4 * a:.2f}")
        stdout.print(table)
        stdout.print("Losses are absorption over the two-way path only (spreading comes on top).")
    if plot is not None:
        from echoloc.plots.physics import plot_air

        written = plot_air(
            plot,
            temperature_c=temperature_c,
            relative_humidity=relative_humidity,
            pressure_pa=pressure_pa,
            frequencies_hz=freqs,
        )
        stderr.print(f"plot written to {written}")


@cli.command(name="beam")
@click.option(
    "--transducer",
    "transducer_name",
    type=click.Choice(list(PRESETS)),
    default="electrostatic50",
    show_default=True,
)
@click.option("--radius-m", type=float, default=None, help="Piston radius, m [default: the preset's].")
@click.option(
    "--frequency", "frequency_hz", type=float, default=None, help="Hz [default: the preset's centre]."
)
@click.option(
    "--speed-of-sound", "speed_of_sound_m_s", type=float, default=343.2, show_default=True, help="m/s."
)
@click.option(
    "--elements", type=click.IntRange(1, 1000), default=1, show_default=True, help="Line array size."
)
@click.option(
    "--spacing-m", type=float, default=None, help="Element spacing, m [default: half a wavelength]."
)
@click.option("--steer-deg", type=float, default=0.0, show_default=True, help="Steering angle, degrees.")
@click.option(
    "--shading", type=click.Choice(["uniform", "hann", "chebyshev"]), default="uniform", show_default=True
)
@click.option(
    "--fov-deg", type=float, default=90.0, show_default=True, help="Field of view to cover, degrees."
)
@click.option("--json", "as_json", is_flag=True, help="One JSON object with the figures.")
@_path_option("--plot", help="Draw the beam pattern (polar).")
def beam_command(
    transducer_name: str,
    radius_m: float | None,
    frequency_hz: float | None,
    speed_of_sound_m_s: float,
    elements: int,
    spacing_m: float | None,
    steer_deg: float,
    shading: ShadingKind,
    fov_deg: float,
    as_json: bool,
    plot: Path | None,
) -> None:
    """Beam widths of a transducer (exact and as the report approximates them), and of a line array."""
    _check_plot(plot)
    preset = PRESETS[transducer_name]
    _finite("--radius-m", radius_m, positive=True)
    _finite("--frequency", frequency_hz, positive=True)
    _finite("--speed-of-sound", speed_of_sound_m_s, positive=True)
    _finite("--spacing-m", spacing_m, positive=True)
    _finite("--steer-deg", steer_deg)
    _finite("--fov-deg", fov_deg, positive=True)
    transducer = replace(preset, radius_m=radius_m) if radius_m is not None else preset
    f = frequency_hz or transducer.centre_frequency_hz
    c = speed_of_sound_m_s
    beam = piston_beam_angles(transducer.radius_m, f, c)
    if not math.isfinite(beam.full_angle_3db_rad):
        raise EchoLocError(
            f"a piston of radius {transducer.radius_m:g} m at {f:g} Hz has ka = {beam.ka:.3g} < 1.616: "
            "it never falls 3 dB, so it has no beam width (raise --radius-m or --frequency)"
        )
    wavelength = c / f
    spacing = spacing_m if spacing_m is not None else wavelength / 2
    steer = math.radians(steer_deg)
    grating = grating_lobe_angles(spacing, f, c, steer) if elements > 1 else np.zeros(0)
    cover = transducers_to_cover(fov_deg, beam.full_angle_3db_deg)
    record: dict[str, Any] = {
        "transducer": transducer.name,
        "radius_m": transducer.radius_m,
        "frequency_hz": f,
        "wavelength_m": wavelength,
        "ka": beam.ka,
        "full_angle_3db_deg": beam.full_angle_3db_deg,
        "report_full_angle_3db_deg": math.degrees(2 * beam.report_half_angle_3db_rad),
        "full_angle_null_deg": beam.full_angle_null_deg,
        "report_full_angle_null_deg": math.degrees(2 * beam.report_half_angle_null_rad),
        "near_field_m": near_field_length_m(transducer.radius_m, f, c),
        "transducers_for_fov": cover,
        "fov_deg": fov_deg,
    }
    if elements > 1:
        record |= {
            "elements": elements,
            "spacing_m": spacing,
            "steer_deg": steer_deg,
            "grating_lobes_deg": [math.degrees(a) for a in grating],
        }
    if as_json:
        click.echo(json.dumps(_json_safe(record), allow_nan=False))
    else:
        table = Table(
            title=f"{transducer.name}: piston radius {transducer.radius_m * 1e3:.2f} mm at {f / 1e3:g} kHz"
        )
        table.add_column("figure")
        table.add_column("exact", justify="right")
        table.add_column("report's approximation", justify="right")
        table.add_row("ka", f"{beam.ka:.2f}", "")
        table.add_row(
            "-3 dB full beam, °",
            f"{beam.full_angle_3db_deg:.2f}",
            f"{record['report_full_angle_3db_deg']:.2f}",
        )
        table.add_row(
            "first nulls, full angle, °",
            f"{beam.full_angle_null_deg:.2f}",
            f"{record['report_full_angle_null_deg']:.2f}",
        )
        table.add_row("near field a²/λ, mm", f"{record['near_field_m'] * 1e3:.1f}", "")
        table.add_row(f"transducers to cover {fov_deg:g}°", str(cover), "")
        if elements > 1:
            lobes = ", ".join(f"{math.degrees(a):.1f}" for a in grating) or "none"
            table.add_row(f"{elements} elements at {spacing * 1e3:.2f} mm: grating lobes, °", lobes, "")
        stdout.print(table)
    if plot is not None:
        from echoloc.plots.physics import plot_beam

        written = plot_beam(
            plot,
            transducer=transducer,
            frequency_hz=f,
            speed_of_sound=c,
            elements=elements,
            spacing_m=spacing,
            steer_rad=steer,
            weights=shading_weights(elements, shading) if elements > 1 else None,
        )
        stderr.print(f"plot written to {written}")


# --- design: uncertainty and receiver spacing --------------------------------------


@cli.command(name="design")
@click.option(
    "--path-m",
    type=float,
    default=None,
    help="Hold the path l = l1 = l2, m, as the report's figure 4.13 does [default: 1.0].",
)
@click.option("--range-m", type=float, default=None, help="Hold the reflector's range instead, m.")
@click.option(
    "--path-error-m", type=float, default=0.005, show_default=True, help="Path error Δl (and path std), m."
)
@click.option(
    "--spacing-m",
    type=float,
    default=None,
    help="Spacing d for the figure 4.12 area and the GDOP map, m [default: the recommended one].",
)
@click.option(
    "--max-cross-range-error-m",
    type=float,
    default=None,
    help="Across-beam error allowed, m [default: the path error].",
)
@click.option(
    "--max-range-error-m", type=float, default=None, help="Range error allowed, m: an upper spacing limit."
)
@_path_option(
    "--scene",
    "scene_path",
    metavar="SCENE.toml",
    help="Array for the GDOP map [default: the report's cross with spacing d].",
)
@click.option("--plane", type=click.Choice(["xz", "yz", "xy"]), default="xz", show_default=True)
@click.option(
    "--offset-m",
    type=float,
    default=None,
    help="Third coordinate of the plane, m [default: 0, or the study's range for the xy plane].",
)
@_path_option("-o", "--output", default=None, help="Directory for the three PNGs.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object with the figures.")
def design_command(
    path_m: float | None,
    range_m: float | None,
    path_error_m: float,
    spacing_m: float | None,
    max_cross_range_error_m: float | None,
    max_range_error_m: float | None,
    scene_path: Path | None,
    plane: str,
    offset_m: float | None,
    output: Path | None,
    as_json: bool,
) -> None:
    """Receiver spacing against range and angle error (report figs 4.12, 4.13) and GDOP maps.

    The default reproduces the report's study: path l = 1 m, path error 5 mm.
    """
    from echoloc.localise.design import design_record, design_study

    for name, value in (
        ("--path-m", path_m),
        ("--range-m", range_m),
        ("--path-error-m", path_error_m),
        ("--spacing-m", spacing_m),
        ("--max-cross-range-error-m", max_cross_range_error_m),
        ("--max-range-error-m", max_range_error_m),
    ):
        _finite(name, value, positive=True)
    _finite("--offset-m", offset_m)
    array = load_scene(scene_path).array if scene_path is not None else None
    study = design_study(
        path_error_m,
        path_m=path_m,
        range_m=range_m,
        spacing_m=spacing_m,
        max_cross_range_error_m=max_cross_range_error_m,
        max_range_error_m=max_range_error_m,
        array_m=None if array is None else (array.transmitters_m, array.receivers_m),
        array_name=None if scene_path is None else str(scene_path),
        plane=plane,  # type: ignore[arg-type]
        offset_m=offset_m,
    )
    held = f"path l = {study.path_m:g} m" if study.path_m is not None else f"range r = {study.range_m:g} m"
    rec, spacing, rows, area = study.recommendation, study.spacing_m, study.table, study.area
    array_name, at_point, area_path = study.array_name, study.on_boresight, study.area_path_m
    record = design_record(study)
    if output is not None:
        from echoloc.plots.design import plot_error_map, plot_spacing_study, plot_uncertainty_area

        try:
            output.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise EchoLocError(f"{output}: cannot create the output directory ({error.strerror})") from None
        written = [
            plot_uncertainty_area(area, output / "uncertainty_area.png"),
            plot_spacing_study(study.curves, rec, output / "spacing_study.png"),
            plot_error_map(study.gdop_map, output / "gdop_map.png", title=array_name),
        ]
        record["plots"] = [str(p) for p in written]
    if as_json:
        click.echo(json.dumps(_json_safe(record), allow_nan=False))
    else:
        table = Table(
            title=f"Spacing study (report fig. 4.13): {held}, Δl1 = ±{path_error_m * 1e3:g} mm, Δl2 = 0"
        )
        for column in (
            "d m",
            "range m",
            "Δr mm",
            "Δr lin mm",
            "Δθ °",
            "Δθ lin °",
            "r·|Δθ| mm",
        ):
            table.add_column(column, justify="right", no_wrap=True)
        table.add_column("", no_wrap=True)
        table.caption = (
            "Δr, Δθ: exact for +Δl1/−Δl1; lin: first order for +Δl1; r·|Δθ|: across-beam error, worst sign"
        )
        for j, d in enumerate(rows.spacings_m):
            mark = math.isclose(d, rec.spacing_m, rel_tol=1e-9)
            chosen = math.isclose(d, spacing, rel_tol=1e-9) and not mark
            table.add_row(
                f"{d:.3f}",
                f"{rows.range_m[j]:.3f}",
                f"{rows.range_error_m[0, j] * 1e3:+.2f}/{rows.range_error_m[1, j] * 1e3:+.2f}",
                f"{rows.linear_range_error_m[0, j] * 1e3:+.2f}",
                f"{math.degrees(rows.angle_error_rad[0, j]):+.2f}/"
                f"{math.degrees(rows.angle_error_rad[1, j]):+.2f}",
                f"{math.degrees(rows.linear_angle_error_rad[0, j]):+.2f}",
                f"{np.max(rows.cross_range_error_m[:, j]) * 1e3:.1f}",
                "◀ recommended" if mark else "◀ chosen" if chosen else "",
                style="bold" if mark else None,
            )
        stdout.print(table)
        limit = (
            f"; at most {rec.largest_spacing_m:.3f} m keeps the range error within "
            f"{rec.max_range_error_m * 1e3:g} mm"
            if rec.largest_spacing_m is not None and rec.max_range_error_m is not None
            else ""
        )
        stdout.print(
            f"Recommended spacing d = {rec.spacing_m:.3f} m ({rec.criterion}){limit}. There: "
            f"range {rec.range_m:.3f} m, |Δr| <= {rec.range_error_m * 1e3:.2f} mm, "
            f"|Δθ| <= {math.degrees(rec.angle_error_rad):.2f}°, "
            f"r·|Δθ| = {rec.cross_range_error_m * 1e3:.2f} mm.",
            highlight=False,
        )
        corners = Table(
            title=f"Uncertainty area (fig. 4.12): d = {spacing:.3f} m, l1 = l2 = {area_path:.3f} m, "
            f"Δl1 = Δl2 = {path_error_m * 1e3:g} mm"
        )
        for column in ("corner", "paths", "x mm", "z m", "Δr mm", "Δθ °"):
            corners.add_column(column, justify="right")
        for k, (name, paths) in enumerate(
            zip("abcd", ("l1+Δl1, l2−Δl2", "l1−Δl1, l2−Δl2", "l1−Δl1, l2+Δl2", "l1+Δl1, l2+Δl2"), strict=True)
        ):
            corners.add_row(
                name,
                paths,
                f"{area.corners_m[k, 0] * 1e3:+.2f}",
                f"{area.corners_m[k, 1]:.4f}",
                f"{(area.corner_range_m[k] - area.range_m) * 1e3:+.2f}",
                f"{math.degrees(area.corner_angle_rad[k] - area.angle_rad):+.3f}",
            )
        stdout.print(corners)
        stdout.print(
            f"{array_name}: on the boresight at {area.range_m:.3f} m, GDOP {float(at_point.gdop):.2f}; "
            f"with σ_path = {path_error_m * 1e3:g} mm, std per axis "
            + ", ".join(f"{v * 1e3:.2f}" for v in at_point.std_m)
            + f" mm, range std {float(at_point.range_std_m) * 1e3:.2f} mm, angle std "
            f"{math.degrees(float(at_point.angle_std_rad)):.3f}°.",
            highlight=False,
        )
    if output is not None:
        for written_path in record["plots"]:
            stderr.print(f"plot written to {written_path}")
