from vislam._launcher import entry_point

entry_point()
