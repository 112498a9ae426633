"""ballbeam-hil: optimal tracking controller bench for the SRV02 ball-and-beam."""
