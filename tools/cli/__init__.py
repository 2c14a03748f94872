"""The command line and the shell: argument parsing, value checks, the live view, the emulate command.
"""
