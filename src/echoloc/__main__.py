"""``python -m echoloc``: the ``echoloc`` command (:func:`echoloc.cli.entry.main`)."""

from echoloc.cli.entry import main

main()
