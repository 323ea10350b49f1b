"""HDF5 artefacts: the files every stage writes and the next one reads.

Guarantees:
- a write goes to a hidden temporary name in the same folder and is renamed
  into place only when complete, so a killed stage leaves no partial artefact;
  a write that fails (a full disk, a quota, an I/O error) removes it and is
  one line naming the output;
- every artefact carries attrs: format version, stage, config digest,
  package version, UTC creation time;
- non-finite floating-point arrays are refused on write and on read;
- inputs are opened read-only with HDF5 file locking off (clusters with NFS);
- a reader checks the attrs and fails with one line naming the file;
- lineage: an artefact written inside `stage_inputs` records the lineage
  digests of the artefacts it was made from, and its own (a digest of its
  config digest, those, and its arrays' contents); inputs read together must
  agree (`check_lineage`). A deterministic rerun with the same settings keeps
  its digest; a rerun that writes other values (another machine, a GPU) gets
  a new one, so files made from the old one are refused until rerun.

Modules: header (format version, attr names, config digest, attr encoding,
opening with the header checked), atomic (atomic writes, full-disk
handling, JSON), lineage (stage_inputs, check_lineage, check_made_from),
writer (write_artefact), reader (read_artefact, open_artefact, partial
reads).
"""

from .atomic import (
    NO_SPACE_ERRNOS,
    WriteFailed,
    atomic_folder,
    atomic_path,
    free_bytes,
    remove_stale_temps,
    write_bytes,
    write_error,
    write_json,
)
from .header import (
    ATTR_CREATED,
    ATTR_DIGEST,
    ATTR_FORMAT,
    ATTR_INPUTS,
    ATTR_LINEAGE,
    ATTR_PACKAGE,
    ATTR_STAGE,
    FORMAT_VERSION,
    RESERVED_ATTRS,
    _decode_attr,
    config_digest,
)
from .lineage import Lineage, check_lineage, check_made_from, read_lineage, stage_inputs
from .reader import (
    Artefact,
    ArtefactAttrs,
    open_artefact,
    read_artefact,
    read_attrs,
    read_dataset,
    read_rows,
    read_tree,
    time_steps_index,
)
from .writer import write_artefact

__all__ = [
    "ATTR_CREATED",
    "ATTR_DIGEST",
    "ATTR_FORMAT",
    "ATTR_INPUTS",
    "ATTR_LINEAGE",
    "ATTR_PACKAGE",
    "ATTR_STAGE",
    "FORMAT_VERSION",
    "NO_SPACE_ERRNOS",
    "RESERVED_ATTRS",
    "Artefact",
    "ArtefactAttrs",
    "Lineage",
    "WriteFailed",
    "_decode_attr",
    "atomic_folder",
    "atomic_path",
    "check_lineage",
    "check_made_from",
    "config_digest",
    "free_bytes",
    "open_artefact",
    "read_artefact",
    "read_attrs",
    "read_dataset",
    "read_lineage",
    "read_rows",
    "read_tree",
    "remove_stale_temps",
    "stage_inputs",
    "time_steps_index",
    "write_bytes",
    "write_artefact",
    "write_error",
    "write_json",
]
