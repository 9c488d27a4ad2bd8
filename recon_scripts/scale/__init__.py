"""What the scale presets (presets.py) run: the photo sets, each stage in its
own measured process, matching per executor, and the tables and plot of the results."""
