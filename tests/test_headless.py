"""Every command on a machine without X11 libraries (issue 39).

On a headless GPU server ``import pyrender`` failed: pyglet, imported for pyrender's viewer,
loads Xlib, and there was no libXrender ("'NoneType' object has no attribute
'XRenderFindVisualFormat'"). This machine has the X11 libraries, so the test takes them away
in a child process: ctypes finds none of them and loading one raises ``OSError``, as dlopen
does there. (Only the libraries Python loads through ctypes, as pyglet and PyOpenGL do; a C
library's own dependencies still load.) In that child every command of the CLI, subcommands
of groups included, answers ``--help``, :func:`~sceneforge.render.raster.import_pyrender`
works, and one small frame of a toy house is rendered on the first EGL device; no X11 module
of pyglet (or python-xlib) is ever imported.

The check has teeth: with pyrender imported as it was before the fix (no headless pyglet)
the same child fails with the server's errors.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("pyrender", reason="pyrender is not installed (pip install 'sceneforge[render]')")

#: the X11 family's libraries, by ctypes name ("X11") or file ("/lib/.../libX11.so.6")
X11_LIBRARIES = (r"X11|X11-xcb|Xext|Xrender|Xi|Xinerama|Xrandr|Xcursor|Xxf86vm|Xfixes|Xss"
                 r"|xcb(-[\w-]+)?|GLX|GLU")

HIDE = textwrap.dedent("""
    # {what}: ctypes finds none of them, and loading one fails as dlopen would
    import ctypes, ctypes.util, os, re
    _missing = re.compile(r"(^|/)(lib)?({names})(\\.so[.\\d]*)?$")
    _find, _init = ctypes.util.find_library, ctypes.CDLL.__init__
    def _find_library(name):
        return None if _missing.search(str(name)) else _find(name)
    def _load(self, name, *args, **kwargs):
        if name and _missing.search(os.fspath(name)):
            raise OSError(f"{{name}}: cannot open shared object file: No such file or directory")
        _init(self, name, *args, **kwargs)
    ctypes.util.find_library = _find_library
    ctypes.CDLL.__init__ = _load
    assert ctypes.util.find_library("{probe}") is None
    try:
        ctypes.CDLL("lib{probe}.so.1")
    except OSError:
        pass
    else:
        raise AssertionError("lib{probe} still loads")
""")

#: pyrender imported as before the fix: pyglet not told it is headless
UNFIXED = textwrap.dedent("""
    import sceneforge.render.raster as raster
    def _unfixed():
        import pyrender
        return pyrender
    raster.import_pyrender = _unfixed
""")

CHILD = textwrap.dedent("""
    import sys
    import click
    import numpy as np
    from click.testing import CliRunner
    from sceneforge.cli.main import cli

    def commands(group, path, ctx):
        for name in group.list_commands(ctx):
            command = group.get_command(ctx, name)
            yield [*path, name]
            if isinstance(command, click.Group):
                sub = click.Context(command, parent=ctx, info_name=name)
                yield from commands(command, [*path, name], sub)

    runner = CliRunner()
    helped = []
    for path in [[], *commands(cli, [], click.Context(cli, info_name="sceneforge"))]:
        res = runner.invoke(cli, [*path, "--help"])
        if res.exit_code != 0 or "Usage:" not in res.output:
            raise SystemExit(f"sceneforge {' '.join(path)} --help: exit {res.exit_code}: {res.output}"
                             f" {res.exception!r}")
        helped.append(" ".join(path))
    print("help:", ", ".join(helped[1:]))

    from sceneforge.render.raster import import_pyrender
    import_pyrender()

    from sceneforge.render import Renderer, egl_devices
    if egl_devices():
        from sceneforge.camera_sampler import CameraSamplerConfig
        from sceneforge.cameras import look_at_camera
        from sceneforge.houses import BUNDLED_TOY, discover, load

        house = load(discover(BUNDLED_TOY)[0])
        room = [i for i in house.instances if i.room_id == house.instances[0].room_id]
        lo = np.min([i.vertices.min(0) for i in room], axis=0)
        hi = np.max([i.vertices.max(0) for i in room], axis=0)
        eye = [(lo[0] + hi[0]) / 2, lo[1] + 1.5, (lo[2] + hi[2]) / 2]
        camera = look_at_camera(eye, CameraSamplerConfig().view_direction(yaw=np.pi / 2), width=64, height=48)
        with Renderer(64, 48) as renderer:
            rgb = renderer.render(house, camera)
            std = rgb.reshape(-1, 3).std(0).max()
            print(f"frame: {rgb.shape} std {std:.1f} on {renderer.gl_info()['renderer']}")
    else:
        print("frame: no EGL device")
    # Xlib (python-xlib), pyglet.libs.x11.*, pyglet.window.xlib, pyglet.gl.xlib, and PyOpenGL's
    # GLX platform (OpenGL.platform.glx: import_pyrender tells PyOpenGL to use EGL)
    x11 = sorted(m for m in sys.modules if {"xlib", "x11", "glx"} & set(m.lower().split(".")))
    print("x11 modules:", x11)
""")

#: what is missing → (the libraries hidden, one to probe, the error of the unfixed import)
MISSING = {
    "no X11 library": (X11_LIBRARIES, "X11", 'ImportError: Library "X11" not found.'),
    "libX11 without libXrender": (  # the server's error
        "Xrender", "Xrender", "AttributeError: 'NoneType' object has no attribute 'XRenderFindVisualFormat'"),
}


def run_child(missing: str, fixed: bool = True) -> subprocess.CompletedProcess:
    names, probe, _ = MISSING[missing]
    code = HIDE.format(what=missing, names=names, probe=probe) + ("" if fixed else UNFIXED) + CHILD
    # no display, and nothing else telling pyglet or PyOpenGL what to do
    env = {k: v for k, v in os.environ.items()
           if k not in ("DISPLAY", "WAYLAND_DISPLAY", "PYOPENGL_PLATFORM") and not k.startswith("PYGLET_")}
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("missing", MISSING)
def test_every_command_runs_without_x11(missing):
    res = run_child(missing)
    assert res.returncode == 0, res.stdout + res.stderr
    lines = dict(line.split(": ", 1) for line in res.stdout.splitlines() if ": " in line)
    helped = lines["help"].split(", ")
    assert {"render", "doctor", "train", "predict", "evaluate", "houses"} <= set(helped), helped
    assert lines["x11 modules"] == "[]", res.stdout
    if lines["frame"] == "no EGL device":
        pytest.skip("commands and pyrender imported without X11; no EGL device to render a frame on")
    assert lines["frame"].startswith("(48, 64, 3)"), res.stdout
    assert float(lines["frame"].split(" std ")[1].split()[0]) > 1.0, res.stdout  # not a blank frame


@pytest.mark.parametrize("missing", MISSING)
def test_the_check_fails_without_the_fix(missing):
    res = run_child(missing, fixed=False)
    assert res.returncode != 0, res.stdout
    assert MISSING[missing][2] in res.stderr.strip().splitlines()[-1], res.stderr
    assert "help: " in res.stdout  # the commands still import: pyrender is imported only when rendering
