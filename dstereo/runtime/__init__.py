"""The runtime machinery around a command: the server and its client, signals and the watchdog, ahead-of-time
executables, the jaxlib workarounds, BLAS threads and the figure workers. Nothing here calibrates or measures;
a command runs the same without it (DSTEREO_SERVE=0 runs every command in its own process)."""
