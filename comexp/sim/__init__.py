"""The simulator side shared by every backend: the scene's vocabulary (`scene`), the engine
interface (`simulator`), the one push protocol (`protocol`, its compiled stop rule `stop_rule`),
and the geometry of pusher, object and camera it needs (`contact`, `view`, `clear_steps`)."""
