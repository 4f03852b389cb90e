"""File names inside a run's output folder (shared by the writers, ``mpipack vtk`` and restart)."""

SNAPSHOT_FILE = "snapshots.h5"     # SnapshotWriter's file
XDMF_FILE = "snapshots.xmf"        # beside it, for ParaView
CHECKPOINT_FILE = "checkpoint.h5"  # write_checkpoint's file
PVD_FILE = "snapshots.pvd"         # convert_run's collection
VTK_DIR = "vtk"                    # convert_run's .vtu files
