"""The interactive web viewer (`dyngs-view`, `dyngs-train --viewer`): a page served from
this machine with the camera under the mouse, a time slider, playback and toggles.

`server.Viewer` serves it (viser) and draws on a background thread; `frames.draw` is the
render path; `resolution.AdaptiveResolution` sizes frames while the view moves;
`camera` converts between the browser's camera and dyngs's; `training.TrainingLink` is
the step hook that shows a training run and pauses it; `options.ViewerOptions` holds the
flags. Import the modules themselves: this package's import loads nothing (the web
server's dependencies load only when a viewer is used).
"""
