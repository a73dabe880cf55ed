"""What a lab meets end to end: user mistakes, damaged footage, failing stages, concurrent runs."""
