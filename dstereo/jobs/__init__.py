"""The jobs: each command's work from files to files (read inputs with `io`, compute with the rooms below, write
the results folder with `io`). `calibrate_camera` / `calibrate_stereo` / `calibrate_cameras` (one, two, N
cameras), `reconstruct` and `reconstruct_pairs` (many pairs as tasks), `refine`, `recession`,
`synthetic_recession` (a rendered sequence written as `dstereo recession` reads it)."""
