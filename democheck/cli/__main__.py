from democheck.cli import app

app()
