"""Wire protocol v1 of the govnesf mapper: messages, validation, (de)serialisation, recordings.

The ground floor of the project: imports nothing else from it.
"""
