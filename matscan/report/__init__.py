"""What a person looks at: contact sheets now; the HTML report and relighting viewer later."""
