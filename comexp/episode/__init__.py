"""The worker side of an episode: its task (`task`: what is pushed, what is scored) and the loop
that runs it on a simulator (`loop.run_episode`). Imports no Hydra and no driver module."""
