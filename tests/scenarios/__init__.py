"""What a lab meets end to end: its own runs set up as labs set them up (``test_lab_*``:
other tools' files, folders, sheets, corrections; helpers in ``lab.py``), user mistakes,
damaged footage, failing stages, concurrent runs."""
