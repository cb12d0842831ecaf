"""The experiment: a job's config and its checks (`config`), the objects, the grid of episodes,
one episode (`episode.run_episode`), and the simulator interface with its push protocol that
the backends implement (`simulator`)."""
