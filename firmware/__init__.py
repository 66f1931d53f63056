"""The firmware's C sources (installed as ``masking_lab.firmware``: its core and POSIX board,
which ``masking_lab.device.host_build`` compiles). Nothing here is Python."""
