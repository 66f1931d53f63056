"""Sub-commands of the masking-lab CLI, one module each (see masking_lab.commands.cli)."""
