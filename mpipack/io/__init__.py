"""Files: parallel HDF5 snapshots (+ XDMF), VTK through meshio, and checkpoints.

Importing this package imports neither h5py nor meshio: each is imported by the function that
needs it, so a run that writes no file never loads them.

    SnapshotWriter(comm, path, n_global, dim, file_attrs)      snapshots.py (layout there)
        .write(local_gid, fields, attrs) / .close()
    write_checkpoint(comm, path, n_global, dim, block, scalars, attrs) -> seconds
    read_checkpoint(comm, path) -> (block, scalars, attrs)    checkpoint.py (layout there)
    convert_run(comm, run_dir) -> [paths]                     vtk.py: .vtu per snapshot + .pvd
    xdmf.write_for(h5_path)                                   xdmf.py: the ParaView index
"""

from .checkpoint import CheckpointError, read_checkpoint, write_checkpoint
from .snapshots import SnapshotError, SnapshotWriter, list_snapshots, read_pairs, read_snapshot
from .names import CHECKPOINT_FILE, PVD_FILE, SNAPSHOT_FILE, VTK_DIR, XDMF_FILE
from .vtk import convert_run

__all__ = ["SnapshotWriter", "SnapshotError", "read_snapshot", "read_pairs", "list_snapshots",
           "write_checkpoint", "read_checkpoint", "CheckpointError", "convert_run",
           "SNAPSHOT_FILE", "XDMF_FILE", "CHECKPOINT_FILE", "PVD_FILE", "VTK_DIR"]
