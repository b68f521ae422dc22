"""``sceneforge doctor``: check the installation, one PASS/WARN/FAIL line per check."""

from __future__ import annotations

import importlib
import importlib.util
import platform
import time
from dataclasses import dataclass
from importlib import metadata

import click

from sceneforge.errors import EXIT_FAILURES, plural

#: (import name, distribution name, what needs it, how to install it)
PACKAGES = (
    ("open3d", "open3d", "ray tracing where the Embree extension is not built", "pip install 'sceneforge[trace]'"),
    ("zarr", "zarr", "the store", "pip install 'sceneforge[store]'"),
    ("torch", "torch", "the models", "pip install torch==2.13.0 'sceneforge[learn]'"),
    ("pyrender", "pyrender", "RGB rendering", "pip install 'sceneforge[render]'"),
    ("OpenGL", "PyOpenGL", "RGB rendering", "pip install 'sceneforge[render]'"),
)


@dataclass(frozen=True)
class Check:
    """The outcome of one check: status PASS, WARN (works, with a caveat) or FAIL."""

    status: str
    name: str
    detail: str
    install: str | None = None


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def check_package(module: str, dist: str, needed_for: str, install: str) -> Check:
    """Import ``module`` (which also loads its system libraries) and report its version."""
    try:
        if module == "pyrender":  # headless, as sceneforge renders: no X11 libraries needed
            from sceneforge.render.raster import import_pyrender

            imported = import_pyrender()
        else:
            imported = importlib.import_module(module)
    except Exception as e:  # any import failure (missing module, missing .so) is what we report
        return Check("FAIL", dist, f"cannot import it ({_first_line(e)}); {needed_for} needs it", install)
    try:
        version = metadata.version(dist)
    except metadata.PackageNotFoundError:
        version = getattr(imported, "__version__", "unknown version")
    return Check("PASS", dist, version)


def check_tracer() -> Check:
    """Which engine traces the layers: sceneforge's Embree extension, else Open3D."""
    from sceneforge.raytrace import default_backend

    if default_backend() == "embree":
        return Check("PASS", "ray tracing", "embree (sceneforge's all-hit extension)")
    return Check("WARN", "ray tracing", "open3d: the Embree extension is not built (same layers, slower)",
                 "install a C++ compiler and Embree's headers (apt-get install g++ libembree-dev), then "
                 "`pip install -e .` again")


def check_cuda() -> Check:
    """Whether torch sees a CUDA device (training runs on the CPU without one)."""
    try:
        import torch
    except Exception:
        return Check("WARN", "torch CUDA", "torch is not importable (see above)")
    if torch.cuda.is_available():
        names = ", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
        return Check("PASS", "torch CUDA", f"{torch.cuda.device_count()} device(s): {names}")
    return Check("WARN", "torch CUDA", f"not available (torch {torch.__version__}): training runs on the CPU")


def check_mitsuba() -> Check:
    """The Mitsuba variant ``--rgb pathtraced`` runs on, and why: set up as path tracing does
    (one tiny kernel, no rendering). Path tracing is optional: a warning without Mitsuba, or
    where no variant runs."""
    from sceneforge.render.pathtrace import INSTALL_MITSUBA, mitsuba_variant

    if importlib.util.find_spec("mitsuba") is None:
        return Check("WARN", "Mitsuba", "not installed: --rgb pathtraced needs it (--rgb raster does not)",
                     INSTALL_MITSUBA)
    try:
        variant = mitsuba_variant()
    except Exception as e:  # no variant runs, or a broken install: what path tracing would say
        return Check("WARN", "Mitsuba", f"--rgb pathtraced will fail: {_first_line(e)}")
    try:
        version = metadata.version("mitsuba")
    except metadata.PackageNotFoundError:
        version = "unknown version"
    return Check("PASS", "Mitsuba", f"{version}, {variant}")


def check_rendering(gpu: int | None) -> list[Check]:
    """EGL devices, the OpenGL strings of a context, and one rendered frame of a toy house."""
    import numpy as np

    from sceneforge.camera_sampler import CameraSamplerConfig
    from sceneforge.cameras import look_at_camera
    from sceneforge.errors import SceneforgeError
    from sceneforge.houses import BUNDLED_TOY, discover, load
    from sceneforge.render import INSTALL_EGL, Renderer, egl_devices

    try:
        devices = egl_devices()
    except SceneforgeError as e:
        return [Check("FAIL", "EGL", str(e))]
    listed = ", ".join(f"{d.index} {d.kind}" + (f" ({d.drm_file})" if d.drm_file else "") for d in devices)
    checks = [Check("PASS" if devices else "FAIL", "EGL devices", listed or "none", None if devices else INSTALL_EGL)]
    if not devices:
        return checks
    house = load(discover(BUNDLED_TOY)[0])
    room = [i for i in house.instances if i.room_id == house.instances[0].room_id]
    lo = np.min([i.vertices.min(0) for i in room], axis=0)
    hi = np.max([i.vertices.max(0) for i in room], axis=0)
    eye = [(lo[0] + hi[0]) / 2, lo[1] + 1.5, (lo[2] + hi[2]) / 2]
    camera = look_at_camera(eye, CameraSamplerConfig().view_direction(yaw=np.pi / 2))
    try:
        with Renderer(camera.width, camera.height, gpu=gpu) as renderer:
            info = renderer.gl_info()
            checks.append(Check("PASS", f"OpenGL on EGL device {renderer.device.index} ({renderer.device.kind})",
                                f"{info['vendor']}, {info['renderer']}, {info['version']}"))
            renderer.render(house, camera)  # compiles the shaders
            start = time.perf_counter()
            rgb = renderer.render(house, camera)
            ms = 1e3 * (time.perf_counter() - start)
            seen = float(np.isfinite(renderer.depth(house, camera)).mean())
    except SceneforgeError as e:
        return [*checks, Check("FAIL", "one-frame render", str(e))]
    ok = seen > 0.5 and rgb.reshape(-1, 3).std(0).max() > 1.0
    checks.append(Check(
        "PASS" if ok else "FAIL", "one-frame render",
        f"{house.id} {camera.width}×{camera.height} in {ms:.1f} ms, {100 * seen:.0f}% of pixels see a surface",
        None if ok else "check the GL driver above; a blank or uniform frame means a broken driver",
    ))
    return checks


def summary_line(checks: list[Check]) -> str:
    """``"11 checks: 10 passed, 1 warning"``: every status counted, none left out of "passed"."""
    counts = {status: sum(c.status == status for c in checks) for status in ("PASS", "WARN", "FAIL")}
    parts = [f"{counts['PASS']} passed"]
    if counts["WARN"]:
        parts.append(plural(counts["WARN"], "warning"))
    if counts["FAIL"]:
        parts.append(f"{counts['FAIL']} failed")
    return f"{plural(len(checks), 'check')}: {', '.join(parts)}"


@click.command("doctor")
@click.option("--gpu", type=click.IntRange(min=0), default=None,
              help="EGL device to render on. Default: $EGL_DEVICE_ID, else the first GPU, else Mesa's software device.")
def doctor(gpu):
    """Check the installation: versions of the optional packages, the ray-tracing engine,
    torch's CUDA, the Mitsuba variant path tracing runs on (CUDA or LLVM, and why), the EGL
    devices and OpenGL driver, and one rendered frame of a bundled toy house. Prints one
    PASS, WARN or FAIL line per check (with what to install for each FAIL) and exits with
    status 3 when a check failed.
    """
    checks = [Check("PASS", "python", platform.python_version())]
    checks += [check_package(*package) for package in PACKAGES]
    checks.append(check_tracer())
    checks.append(check_cuda())
    checks.append(check_mitsuba())
    checks += check_rendering(gpu)
    colours = {"PASS": "green", "WARN": "yellow", "FAIL": "red"}
    for c in checks:
        click.echo(click.style(f"{c.status:<5}", fg=colours[c.status]) + f" {c.name}: {c.detail}")
        if c.install:
            click.echo(f"      install: {c.install}")
    click.echo(summary_line(checks))
    failed = sum(c.status == "FAIL" for c in checks)
    if failed:
        click.get_current_context().exit(EXIT_FAILURES)
