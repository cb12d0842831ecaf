"""The experiment: a job's config and its checks (`config`), the objects, the grid of episodes,
an episode's task (`task`) and the loop that runs it (`episode.run_episode`), the simulator
interface with its push protocol that the backends implement (`interface`), the backends by
name (`registry`), and the camera-view and contact geometry they share (`view`, `contact`);
`simulator` re-exports those four."""
