"""``view.py``: a ParaView Python script written beside a run's snapshots, that shows them.

    <folder>/view.py    written by SnapshotWriter (every run that writes snapshots) and by
                        ``mpipack vtk``; rewritten each time (copy it to change it)

Run it with ParaView's own Python, headless (pvbatch needs a display: ``xvfb-run`` gives one;
``-noreset``, because an Xvfb that resets when pvbatch's first connection closes refuses the
next: 1 run in 8 failed without it here, none of 8 with it)::

    xvfb-run -a -s "-screen 0 1280x1024x24 -noreset" pvbatch view.py --png view.png [--iteration K] [--vtk]

or in the ParaView GUI: View > Python Shell > Run Script. It opens ``<stem>.xmf`` beside it
(``--vtk``: ``<stem>.pvd`` of ``mpipack vtk``) and shows every sphere to scale (a sphere glyph of
radius 1 scaled by the ``radius`` array, scale factor 1) coloured by pressure, and, when
``<stem>_contacts.xmf`` (``.pvd``) exists, the contact network (a line per pair with
lambda > 0, the force chains) as tubes coloured by lambda, at the last snapshot (or iteration
K), and ``container.vtu`` (io/container_mesh.py: a run's container) as an outline in 1D and
2D, a translucent surface in 3D. In 1D and 2D the spheres lie in z = 0, seen from +z, the network lifted in front of them; in
3D the spheres are translucent so that the network inside shows. ``--png`` saves the picture.

This module only writes the text; it imports nothing of ParaView.
"""

import os

from . import _h5

VIEW_FILE = "view.py"

_SCRIPT = '''"""ParaView view of an mpipack run (written by mpipack beside its snapshots; rewritten).

    xvfb-run -a -s "-screen 0 1280x1024x24 -noreset" pvbatch view.py --png view.png [--iteration K] [--vtk]
    ParaView GUI: View > Python Shell > Run Script (this file)

Spheres to scale (glyphs of the radius array) coloured by pressure; the contact network (pairs
with lambda > 0: the force chains) as tubes coloured by lambda; the last snapshot or iteration K.
Reads STEM.xmf and STEM_contacts.xmf beside this file (--vtk: STEM.pvd, STEM_contacts.pvd),
and shows container.vtu (a run with a container: its walls) as an outline (1D, 2D) or a
translucent surface (3D).
"""
import argparse
import os
import sys

from paraview.simple import (ColorBy, ExtractSurface, GetActiveViewOrCreate, GetAnimationScene,
                             GetColorTransferFunction, GetScalarBar, Glyph, OpenDataFile, Render,
                             SaveScreenshot, Show, Transform, Tube)

STEM = @STEM@
CONTAINER = "container.vtu"
HERE = os.path.dirname(os.path.abspath(globals().get("__file__") or "view.py"))
ap = argparse.ArgumentParser(description="ParaView view of an mpipack run")
ap.add_argument("--png", help="save the picture to this PNG file")
ap.add_argument("--iteration", type=int, help="the snapshot of this iteration (default: the last)")
ap.add_argument("--vtk", action="store_true", help="read the .pvd files of mpipack vtk")
args, _ = ap.parse_known_args(sys.argv[1:])
ext = ".pvd" if args.vtk else ".xmf"

spheres = OpenDataFile(os.path.join(HERE, STEM + ext))
times = spheres.TimestepValues
times = list(times) if hasattr(times, "__len__") else [times]  # one snapshot: a number
t = times[-1] if args.iteration is None else float(args.iteration)
if t not in times:
    sys.exit(f"view.py: no snapshot of iteration {args.iteration} (there are {[int(x) for x in times]})")
view = GetActiveViewOrCreate("RenderView")
scene = GetAnimationScene()
scene.UpdateAnimationUsingDataTimeSteps()
scene.AnimationTime = view.ViewTime = t
spheres.UpdatePipeline(t)
radius = "radius" if "radius" in spheres.PointData.keys() else "diameter"  # files before radius
r_max = spheres.PointData[radius].GetRange()[1] * (1.0 if radius == "radius" else 0.5)
bounds = spheres.GetDataInformation().GetBounds()
flat = bounds[4] == bounds[5]  # 1D and 2D: z = 0
network = os.path.join(HERE, STEM + "_contacts" + ext)
if os.path.exists(network):  # shown when the snapshot holds contacts (none at the start)
    network = OpenDataFile(network)
    network.UpdatePipeline(t)
    network = network if network.GetDataInformation().GetNumberOfCells() > 0 else None
else:
    network = None

balls = Glyph(Input=spheres, GlyphType="Sphere", GlyphMode="All Points")
balls.OrientationArray = ["POINTS", "No orientation array"]
balls.ScaleArray = ["POINTS", radius]
balls.ScaleFactor = 1.0 if radius == "radius" else 0.5
balls.GlyphType.Radius = 1.0
fine = spheres.GetDataInformation().GetNumberOfPoints() <= 20000  # coarser spheres for many
balls.GlyphType.ThetaResolution, balls.GlyphType.PhiResolution = (32, 16) if fine else (10, 6)
shown = Show(balls, view)
ColorBy(shown, ("POINTS", "pressure"))
shown.SetScalarBarVisibility(view, True)
if network is not None and not flat:
    shown.Opacity = 0.3

if network is not None:
    lines = ExtractSurface(Input=network)
    if flat:  # in front of the discs, seen from +z
        lines = Transform(Input=lines)
        lines.Transform.Translate = [0.0, 0.0, 1.05 * r_max]
    net = Show(Tube(Input=lines, Radius=0.15 * r_max, NumberofSides=12), view)
    ColorBy(net, ("CELLS", "lambda"))
    lut = GetColorTransferFunction("lambda")
    lut.ApplyPreset("Inferno (matplotlib)", True)
    net.SetScalarBarVisibility(view, True)
    GetScalarBar(lut, view).WindowLocation = "Upper Left Corner"

container = os.path.join(HERE, CONTAINER)
if os.path.exists(container):  # the walls (mpipack's container.vtu): outline or translucent surface
    walls = Show(OpenDataFile(container), view)
    walls.ColorArrayName = ["POINTS", ""]  # one colour
    walls.AmbientColor = walls.DiffuseColor = [0.45, 0.55, 0.75]
    walls.LineWidth, walls.PointSize = 3.0, 10.0
    if not flat:
        walls.Opacity = 0.2

view.OrientationAxesVisibility = 0
if flat:
    view.InteractionMode = "2D"
    view.CameraPosition, view.CameraFocalPoint, view.CameraViewUp = [0, 0, 1], [0, 0, 0], [0, 1, 0]
else:
    view.CameraPosition, view.CameraFocalPoint, view.CameraViewUp = [1, -1.5, 1], [0, 0, 0], [0, 0, 1]
view.ResetCamera()
Render(view)
if args.png:
    SaveScreenshot(args.png, view, ImageResolution=[1200, 900])
    print(f"view.py: iteration {int(t)} -> {args.png}")
'''


def view_path(folder):
    return os.path.join(os.fspath(folder), VIEW_FILE)


def script(stem="snapshots"):
    """The text of view.py for the files ``<stem>.xmf`` etc."""
    return _SCRIPT.replace("@STEM@", repr(stem))


def write_view(folder, stem="snapshots"):
    """Write ``<folder>/view.py`` (atomically, serial: call on one rank); returns its path."""
    path = view_path(folder)
    _h5.write_text_atomic(path, script(stem))
    return path
