"""The warehouse map: inventory of a run's load map against the warehouse system's manifest
(`inventory`), load maps merged across flights (`merge`), and the interactive 3D view
(`view3d`, report.html).  Input files are parsed in `manifest`; output escaping is in `escape`."""
