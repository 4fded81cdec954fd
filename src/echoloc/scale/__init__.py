"""Beyond one process: many recordings (``echoloc batch``) and design studies
(``echoloc sweep``) on a Dask cluster, local or remote (the ``cluster`` extra)."""
