"""What every report of the tool shares: numbers for people (text), figures without a display
(figures), the self-contained HTML page (html) and where Rerun data go (rerun). Imported
module by module: figures need matplotlib and rerun the Rerun SDK, only when drawn."""
