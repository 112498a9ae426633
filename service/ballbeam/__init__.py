"""ballbeam-hil: optimal tracking controller bench for the SRV02 ball-and-beam.

Importing the package changes nothing of the importing program (its environment included): the
processes of our own set their BLAS thread limits where they start (``ballbeam.entry``)."""
