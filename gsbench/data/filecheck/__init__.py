"""Fast structural checks of input files, run before a third-party reader (pycolmap, open3d, numpy,
scipy) sees them, so that a damaged file gives a one-line `DataError` naming it instead of a hang, an
unbounded allocation or silently wrong data.

Every check compares what a file's header promises with the file's size, without decoding payloads:

- COLMAP binary models (`colmap.check_colmap_binary`): the uint64 record count, then each record's fixed
  part and its variable-length part (points3D tracks, images' names and points2D, cameras' params by
  model id, rigs' sensors, frames' data ids); a record that runs past the end of the file, or bytes
  left after the last record, is an error. pycolmap's reader loops over the count it reads and, on a
  truncated ``points3D.bin``, spins on a failed stream while allocating (observed: ~40 MB/s until
  killed). A points3D file is walked with one Python step per record (0.15-0.3 s for a million
  points with tracks of 2-10, a 99 MB file, on 2 cores), or with one vectorised step when all tracks
  have the same length (e.g. empty, as gsbench writes them: 0.01 s per million).
- COLMAP text models cannot hang pycolmap (it stops at the first line it cannot parse, in
  milliseconds), but its message names neither the file nor the line: `colmap.locate_colmap_text_error`
  finds them after pycolmap has failed. A text file cut at a line boundary reads without an error;
  `colmap.colmap_text_count_problem` compares the ``# Number of cameras/points`` comment with what was read.
- PLY (`ply.check_ply`): the header (``ply``, ``format``, ``element``/``property`` lines, ``end_header``),
  then for binary formats each element's records against the bytes left (list properties are
  checked vectorised when every list of an element has the same length, else per record), for ASCII
  the number of lines. open3d reads a truncated binary PLY without an error (the missing points come
  back as garbage) and allocates whatever ``element vertex N`` asks for.
- NPZ (`arrays.check_npz`): a zip archive whose members are ``.npy`` arrays without pickled objects, each
  member's CRC and size matching the shape and dtype its header declares (so `np.load` neither
  allocates for a lying header nor fails later with an unhandled ``BadZipFile``/``EOFError``).
- MATLAB ``.mat`` (`arrays.check_mat`), a 4x4 text matrix (`arrays.read_matrix4_text`), an open3d crop
  volume ``.json`` (`arrays.check_crop_json`), a TnT ``.log`` (`arrays.check_log`): the variables/keys/values the
  evaluators need.

Messages read ``<file> is damaged: <what>; fix: <fix>`` (`common.damaged`).
"""
