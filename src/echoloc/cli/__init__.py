"""The ``echoloc`` command line. Kept light: ``echoloc.cli.entry`` imports the commands
(``echoloc.cli.commands``) under a guard."""
