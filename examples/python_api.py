from temoto import ActionEngine, action, catalog, graph


@action(outputs={"text": str})
def hello():
    return {"text": "hello"}


@action(inputs={"text": str}, outputs={"text": str})
def shout(text):
    return {"text": text.upper() + "!"}


with ActionEngine(actions=catalog(hello, shout)) as engine:
    print(engine.run(graph(hello, shout)).outputs)  # {'text': 'HELLO!'}
