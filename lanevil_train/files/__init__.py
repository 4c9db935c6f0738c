"""Writing and reading files safely, for every layer: atomic writes (a reader never sees half a file, a kill
leaves only recognisable temporaries) and JSON-lines reading with file:line errors. A leaf: it imports nothing of
lanevil_train, so models, data, reports and tasks can all use it without reaching into one another."""
