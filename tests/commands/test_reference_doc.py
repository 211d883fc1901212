"""docs/reference.md's generated block is `dstereo.commands.reference_doc.markdown()`: every command and option as
the command line declares them. When a flag, its help or a default changes, rewrite the page with
`python -m dstereo.commands.reference_doc --write`."""

from dstereo.commands.reference_doc import BEGIN, END, PAGE, generated_block, markdown, replace_block


def test_the_page_holds_the_generated_block():
    page = PAGE.read_text()
    assert page.count(BEGIN) == 1 and page.count(END) == 1, f"{PAGE}: one BEGIN and one END marker"
    assert generated_block(page) == markdown(), f"{PAGE}: run `python -m dstereo.commands.reference_doc --write`"


def test_every_command_and_flag_is_in_the_block():
    from dstereo.commands.reference_doc import _click_group

    block = markdown()
    group = _click_group()
    for name, command in group.commands.items():
        assert f"### `dstereo {name}`" in block, name
        for p in command.params:
            if p.param_type_name == "option" and not getattr(p, "hidden", False):
                assert f"`{p.opts[0]}" in block, (name, p.opts)


def test_replace_block_keeps_the_hand_written_text():
    page = f"# head\n\n{BEGIN}\nold\n{END}\n\n## tail\n"
    new = replace_block(page, "new\n")
    assert new == f"# head\n\n{BEGIN}\nnew\n{END}\n\n## tail\n"
    assert generated_block(new) == "new\n"
