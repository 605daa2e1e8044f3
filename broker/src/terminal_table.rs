//! Aligned text tables, for the commands that print what the admin endpoint answers
//! (`fbbus devices`, `fbbus sessions`): each column as wide as its widest cell (counted in
//! characters: ids are any UTF-8), two spaces between columns, no trailing blanks.

/// `rows` (the header first) as aligned lines, each ending in a newline.
pub fn aligned<const N: usize>(rows: &[[String; N]]) -> String {
    let widths: Vec<usize> = (0..N)
        .map(|c| rows.iter().map(|r| r[c].chars().count()).max().unwrap_or(0))
        .collect();
    let mut out = String::new();
    for row in rows {
        let cells: Vec<String> = row
            .iter()
            .zip(&widths)
            .map(|(cell, w)| format!("{cell:<w$}"))
            .collect();
        out.push_str(cells.join("  ").trim_end());
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn columns_align_on_characters_not_bytes() {
        let rows = [
            ["ID".to_owned(), "STATUS".to_owned()],
            ["förderband".to_owned(), "online".to_owned()],
        ];
        assert_eq!(
            super::aligned(&rows),
            "ID          STATUS\nförderband  online\n"
        );
    }
}
