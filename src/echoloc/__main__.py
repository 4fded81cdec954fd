"""``python -m echoloc``: the ``echoloc`` command (:func:`echoloc.entry.main`)."""

from echoloc.entry import main

main()
