"""mode=play: watch and steer falls live in the browser.

- `session`: the falls, run by mode=eval's paired rollout and scored by its metrics (no drawing);
- `scene`: the 3-D scene in viser (robots side by side, ghosts, contact-force arrows);
- `panel`: the page's controls, the peak-force bars and the metrics table;
- `server`: `run_play`, the viser server and the background player that paces and draws falls.

Nothing in fallkit imports this package but the app (`MODES["play"]`).
"""
