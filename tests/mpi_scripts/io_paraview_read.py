"""Read files with ParaView the way a user's pvpython would, and report what it saw.

    pvpython io_paraview_read.py FILE...    (absolute paths: .xmf or .pvd)

Prints one JSON line per file: the reader ParaView chose, the time steps, and for every time
step the number of points and cells, the point-data array names, and the points and the
diameter/pressure/contacts values at the first, middle and last point (Python floats, so the
test can compare them exactly). Runs under ParaView's own Python (no numpy needed).
"""

import json
import sys

from paraview import servermanager as sm
from paraview.simple import OpenDataFile


def first_dataset(d):
    # multiblock outputs (some readers wrap the grid) -> the first leaf
    while d is not None and d.IsA("vtkMultiBlockDataSet"):
        d = d.GetBlock(0)
    return d


def describe(path):
    r = OpenDataFile(path)
    if r is None:
        return {"path": path, "error": "OpenDataFile returned None"}
    times = list(getattr(r, "TimestepValues", None) or [])
    if isinstance(getattr(r, "TimestepValues", None), float):
        times = [r.TimestepValues]
    steps = []
    for t in (times or [None]):
        if t is None:
            r.UpdatePipeline()
        else:
            r.UpdatePipeline(t)
        d = first_dataset(sm.Fetch(r))
        n = d.GetNumberOfPoints()
        pd = d.GetPointData()
        names = [pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays())]
        sample = sorted({0, n // 2, n - 1}) if n else []
        vals = {}
        for name in ("diameter", "pressure", "contacts"):
            a = pd.GetArray(name)
            if a is not None:
                vals[name] = [a.GetComponent(i, 0) for i in sample]
        steps.append({"time": t, "points": n, "cells": d.GetNumberOfCells(), "arrays": names,
                      "sample": sample, "xyz": [list(d.GetPoint(i)) for i in sample], "values": vals})
    return {"path": path, "reader": r.GetXMLName(), "times": times, "steps": steps}


for p in sys.argv[1:]:
    print(json.dumps(describe(p)), flush=True)
