"""`mpsim bench` suites, one file per model family, and their measuring tools."""
