"""The pipeline: the networks run stage by stage (`reconstruct`), and the mesh options with the steps after the
networks (`options`)."""
