"""The jobs: each command's work from files to files (read inputs with `io`, compute with the rooms below, write
the results folder with `io`). Calibration is one job for any number of cameras (`calibrate_cameras.calibrate_rig`:
`--images` K = 1, `--left/--right` and the thesis's stereo layout K = 2 through `calibrate_stereo`, `--cameras` K = N),
each camera's stage in `calibrate_camera`; `reconstruct` and `reconstruct_pairs` (many pairs as tasks), `refine`,
`recession`, `synthetic_recession` (a rendered sequence written as `dstereo recession` reads it)."""
